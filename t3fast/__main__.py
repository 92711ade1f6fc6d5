"""``python -m t3fast``: the command line (also under torchrun: ``torchrun -m t3fast train-wm ...``)."""

import sys

from t3fast.commands.main import main

sys.exit(main())
