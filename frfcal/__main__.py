import sys

from frfcal.cli import main

sys.exit(main())
