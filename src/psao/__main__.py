import sys

from psao.cli import main

sys.exit(main())
