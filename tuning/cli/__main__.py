"""``python -m tuning.cli``: the ``diffpen`` command."""
import sys

from . import main

sys.exit(main())
