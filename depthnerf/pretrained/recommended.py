"""The shipped checkpoint the demo and the app use for each category, kept free of torch so that ``depthnerf app
--help`` and the app's missing-extra message stay instant (the weights themselves: :mod:`~depthnerf.pretrained.load`).
"""

RECOMMENDED = {"cars": "cpu-cars-sym-pp", "chairs": "cpu-chairs-sym-pp"}
"""The best shipped checkpoint per category, used by default by ``depthnerf demo`` and ``depthnerf app``: of the
shipped models evaluated on the same protocol, the one with the highest PSNR (its card's ``metrics``), which also
passes the mesh gate on the app's photos (docs/RESULTS.md, Table 1 and the mesh gate). A model shipped later that
beats one replaces it here (``tests/test_shipped_models.py`` checks the ranking)."""
