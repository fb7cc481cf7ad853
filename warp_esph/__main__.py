"""``python -m warp_esph``: the ``warp-esph`` command line (see ``warp_esph.cli``)."""

import os
import signal
import sys


def _early_exit(signum, frame):
    # Ctrl-C before the command line has installed its own handlers: nothing is open yet.
    os.write(2, b"warp-esph: interrupted\n" if signum == signal.SIGINT else b"warp-esph: terminated\n")
    os._exit(130 if signum == signal.SIGINT else 143)


# First of all, before anything heavy is imported (warp_esph itself loads nothing heavy).
# A signal the process was started ignoring (a background job of a script) stays ignored.
for _sig in (signal.SIGINT, signal.SIGTERM):
    if signal.getsignal(_sig) is not signal.SIG_IGN:
        signal.signal(_sig, _early_exit)

from .cli import console_main  # noqa: E402

sys.exit(console_main())
