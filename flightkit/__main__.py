import sys

from flightkit.cli.main import main

sys.exit(main())
