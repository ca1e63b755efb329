"""The order of the parameter vector P that every generated function of the dynamics
takes (:mod:`leglib.model.derivation` writes them, :func:`leglib.model.terms.param_vector`
fills P). Its own module, so that the compiled terms do not import sympy with the
derivation (about 0.4 s in every process that simulates the leg)."""

PARAM_NAMES = ("l1", "l2", "l3", "l4", "m1", "m2", "m3", "m4", "lc1", "lc2", "lc3", "lc4",
               "I1", "I2", "I3", "I4", "Jd1", "Jd2", "g")
