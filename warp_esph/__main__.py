"""``python -m warp_esph``: the ``warp-esph`` command line (see ``warp_esph.cli``)."""

import sys

from .cli import main

sys.exit(main())
