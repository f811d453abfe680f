"""``python -m retarget_core.cli``: the ``handretarget`` command."""

import sys

from . import main

sys.exit(main())
