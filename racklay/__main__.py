import sys

from racklay.cli import main

sys.exit(main())
