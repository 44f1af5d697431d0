"""``python -m service.jobs``: run inversion workers (see :mod:`service.jobs.worker`)."""

import sys

from service.jobs.worker import main

sys.exit(main())
