"""``python -m workers.demo`` (``make demo``): see :mod:`workers.demo.run`."""

import sys

import numpy as np

from workers.demo.run import main

np.set_printoptions(suppress=True)
sys.exit(main())
