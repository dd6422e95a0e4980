from mocapflow.pipeline.cli import main

raise SystemExit(main())
