"""``python -m gpumap.commands ...``: the same as the ``gpumap`` command."""

import sys

from gpumap.commands import main

sys.exit(main())
