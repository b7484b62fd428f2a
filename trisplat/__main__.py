import sys

from trisplat.cli import main

sys.exit(main())
