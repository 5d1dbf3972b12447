"""`python -m streamer.cli ...` is `pvt ...` (also how `pvt demo` starts `pvt sim` as its second process)."""

import sys

from streamer.cli import main

sys.exit(main())
