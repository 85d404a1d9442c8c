import sys

from fieldbus.cli import main

sys.exit(main())
