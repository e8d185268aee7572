"""Adapting a model: the options and their defaults (``config``), the loop (``loop``) and its
resumable state (``state``), the official 3DGS learning rates, position schedule and Adam groups
(``official``), fine-tuning (``finetune``), the leave-out (``pruning``), the merged tiers and the
tree's fit (``tiers``, ``tree_fit``), data-parallel runs (``distributed``)."""
