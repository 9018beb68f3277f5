"""``python -m evseg_torch.app.cli``: the ``evseg`` command."""

import sys

from evseg_torch.app.cli.entry import main

sys.exit(main())
