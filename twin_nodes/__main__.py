import sys

from twin_nodes.cli import main

sys.exit(main())
