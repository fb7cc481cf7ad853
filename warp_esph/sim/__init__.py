"""The simulation: the kernels of the method and the ``Solver`` that schedules them.

One module per stage of the step (docs/physics.md has the table of which equation lives
where): ``smoothing`` (kernels W; the fit weights' names in ``fit_weights``, which imports no
Warp), ``neighbors``, ``materials`` (the per-material arrays
as one struct), ``plasticity``, ``forces`` (stress, elastic pair forces), ``pressure``
(SPH), ``deformation``, ``integrate`` with ``colliders``, ``fields``, ``comparison`` (the
Fig. 8 deformation models), ``ghost_floor`` (the no-slip floor of odd ghosts), ``fused``
(the forward-only schedule), ``solver``.

Each module's factories (``funcs``, ``kernels``, ...) are ``functools.cache``d on the scalar
type, names and counts: what they keep for the process is Warp functions, kernels and
structs, compiled once and never changed, and no array or model, so every solver, model and
thread may share them.
"""
