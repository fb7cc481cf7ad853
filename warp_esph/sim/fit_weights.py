"""The fit's weights by name, apart from their kernels: this module imports no Warp, so the
validation suite (``benchmarks/validation.py``), which must not load Warp, reads the very
names ``smoothing`` builds its kernels for (``smoothing.fit_weight_funcs``)."""

#: The weights of the incremental fit (eq. 7) and of every sum that shares them (the
#: variational force's pairs, the curvature-corrected fit's moments, the neighbourhood guard's
#: moment matrix): ``"poly6"``, the paper's ``(h^2 - r^2)^3``; ``"biweight"``, ``(h^2 - r^2)^2``,
#: which gives the second neighbours more weight against the first, so that a particle's fitted
#: increment shares more of its neighbours' (docs/physics.md, "The fit's weight"). The SPH
#: density, the hourglass control and the ghost floor's stencil keep poly6.
FIT_WEIGHTS = ("poly6", "biweight")
#: The weight a model gets unless it names one (``SceneBuilder``, ``Model``, a scene file's
#: ``[solver]``, the neighbour search): the biweight since 2026-12-06, for the large-strain flow
#: stress and the S = 0.3 slump height it keeps with every target poly6 meets (docs/physics.md,
#: "The fit weight's default: the evidence"). Poly6, the paper's eq. 7, stays selectable by name.
#: The test suite's bounds hold under either weight; docs/validation.md's rows carry their
#: weight, and a row written before the option was poly6's.
DEFAULT_FIT_WEIGHT = "biweight"
