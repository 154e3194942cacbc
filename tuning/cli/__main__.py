"""``python -m tuning.cli ...``: the ``diffpen`` command from a checkout."""
import sys

from . import main

sys.exit(main())
