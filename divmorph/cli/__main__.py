"""``python -m divmorph.cli``: the ``divmorph`` command."""

import sys

from divmorph.cli import main

sys.exit(main())
