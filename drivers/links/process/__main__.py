"""``python -m drivers.links.process <backend>``: a link's child process (:mod:`.child`)."""

import sys

from .child import main

sys.exit(main())
