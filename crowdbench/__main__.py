"""``python -m crowdbench ...`` = the ``crowdbench`` command."""

import sys

from crowdbench.entry import main

sys.exit(main())
