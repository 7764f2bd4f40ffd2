"""``python -m umi_aug`` = the ``umi-aug`` command."""

import sys

from umi_aug.cli import main

sys.exit(main())
