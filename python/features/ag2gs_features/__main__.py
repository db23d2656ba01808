"""`python -m ag2gs_features`: the same as the ag2gs-features command."""

import sys

from .cli import main

sys.exit(main())
