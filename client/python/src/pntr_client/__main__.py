"""`python -m pntr_client ...`: the same command line as the `pntr-client` script."""

import sys

from pntr_client.cli import main

sys.exit(main())
