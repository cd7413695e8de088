"""``python -m jaxdrive.cli``: the ``jaxdrive`` command without the console script."""

import sys

from jaxdrive.cli import main

sys.exit(main())
