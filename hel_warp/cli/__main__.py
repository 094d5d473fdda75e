"""``python -m hel_warp.cli``: the ``hel-warp`` command without its console script."""

import sys

from hel_warp.cli import main

sys.exit(main())
