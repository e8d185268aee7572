"""The level-of-detail mechanism: the rule (Eq. 2, ``rule``), one camera's terms (``view``), what a
frame draws (``draw``), the merge tree and its cut (``tree``, ``cut``), budgets and their cost
(``budget``, ``cost``), the static rankings (``rankings``) and the renderer hook (``hook``)."""
