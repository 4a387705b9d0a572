"""``python -m mosiv_ros``: the ``mosiv`` command line."""

from mosiv_ros.cli import main

raise SystemExit(main())
