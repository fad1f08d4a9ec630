"""``python -m unimal_envs.morphology``: same as the ``unimal-morphologies`` command."""

import sys

from unimal_envs.morphology.cli import main

sys.exit(main())
