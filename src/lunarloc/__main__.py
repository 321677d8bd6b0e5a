import sys
from lunarloc.cli import main

sys.exit(main())
