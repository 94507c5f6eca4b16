from gear.cli import main

raise SystemExit(main())
