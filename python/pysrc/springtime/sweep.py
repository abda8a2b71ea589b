"""`python -m springtime.sweep PLAN [--out DIR] [--address HOST:PORT]`: a sweep plan's jobs as
Ray tasks (the command line of `springtime.sweep`, implemented in `springtime._ray`)."""

import sys

from ._ray import main

if __name__ == "__main__":
    sys.exit(main())
