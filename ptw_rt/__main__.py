"""`python -m ptw_rt` is `ptw-rt`."""

import sys

from ptw_rt.cli import main

sys.exit(main())
