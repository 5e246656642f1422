import sys

from hood_decomp.cli import main

sys.exit(main())
