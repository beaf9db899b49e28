"""`python -m recoil_jax.apps._cli ...`: the command line, as `recoil-jax ...`."""

import sys

from .parser import main

sys.exit(main())
