"""``python -m mocapflow``: the ``mocapflow`` command (:func:`mocapflow.pipeline.cli.main`)."""

from mocapflow.pipeline.cli import main

raise SystemExit(main())
