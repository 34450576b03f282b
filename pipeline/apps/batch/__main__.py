"""``python -m pipeline.apps.batch FILE ...``: the same as ``python -m pipeline batch FILE
...`` (:func:`pipeline.cli.batch.main`)."""

import sys

from pipeline.cli.batch import main

sys.exit(main())
