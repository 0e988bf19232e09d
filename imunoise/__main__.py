import sys

from imunoise.cli import main

sys.exit(main())
