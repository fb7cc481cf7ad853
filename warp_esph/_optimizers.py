"""The optimisers ``fit.fit`` runs, named once for the library, ``warp-esph fit``'s parser and
the examples (``fit.OPTIMIZERS``): each had its own copy of the names, which a new optimiser
would have left behind. Apart from ``fit.py`` so that the command line's parser reads them
without importing Warp.
"""

#: ``fit``'s ``optimizer`` values, ``"adam"`` (its default) first.
OPTIMIZERS = ("adam", "lbfgs", "gauss-newton")
#: Those whose steps ``lr`` sizes (their first step moves by it); Gauss-Newton's damping sizes
#: its own and never reads ``lr``.
LR_OPTIMIZERS = ("adam", "lbfgs")
