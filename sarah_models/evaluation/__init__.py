"""The paper's evaluation: metrics (a registry), the Random and NN baselines, Table 1 and
Table 2 (``runner.run_evaluation``, formatted by ``tables.py``)."""
