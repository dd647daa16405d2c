"""``python -m fieldtool.cli``: the same entry point as the ``fieldtool`` script."""

from fieldtool.cli.main import main

raise SystemExit(main())
