"""``python -m jaxelastic …``: the same as the ``jaxelastic`` command (:mod:`jaxelastic.cli`)."""

import sys

from .cli import main

sys.exit(main())
