"""The level-of-detail mechanism: the rule (Eq. 2), a camera's view and what it draws, the merge tree, budgets and their cost, the static rankings, the renderer hook."""
