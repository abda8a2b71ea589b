"""springtime: learn simulatable mass-spring cloth from motion.

The native extension (`springtime._springtime`) does the work: `load_run`, `train`, `evaluate`,
`Run.simulate`, and the sweep contract (`sweep_list`, `sweep_index`, `sweep_gather`).
`springtime.sweep` runs a sweep plan on a Ray cluster (`pip install "./python[ray]"`).
"""

from ._springtime import *  # noqa: F401,F403
from ._springtime import __doc__ as _native_doc  # noqa: F401
from ._springtime import __version__  # noqa: F401
from ._ray import sweep  # noqa: F401
