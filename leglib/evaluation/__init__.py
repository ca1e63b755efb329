"""How wrong each method is: every method scored on every twin plant
(:mod:`~leglib.evaluation.robustness`)."""
