"""Adapting a model: the configuration and the loop, fine-tuning, the leave-out, the merged tiers and the tree's fit, data-parallel runs."""
