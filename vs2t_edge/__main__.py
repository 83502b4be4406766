import sys

from vs2t_edge.cli import main

sys.exit(main())
