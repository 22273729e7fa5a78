import sys

from partinspect.cli import main

sys.exit(main())
