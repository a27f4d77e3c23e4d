import sys

from jaxest.cli import main

sys.exit(main())
