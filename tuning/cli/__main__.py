"""``python -m tuning.cli``: the ``diffpen`` command."""
from . import entry

entry()
