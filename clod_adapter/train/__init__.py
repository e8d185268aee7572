"""Adapting a model: the options (``config``), the loop (``loop``) and its resumable state
(``state``), fine-tuning (``finetune``), the leave-out (``pruning``), the merged tiers and the
tree's fit (``tiers``, ``tree_fit``), data-parallel runs (``distributed``)."""
