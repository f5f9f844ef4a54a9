import sys

from slam2d.cli.main import main

sys.exit(main())
