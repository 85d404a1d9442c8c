"""``python -m sim_slaves.ethercat``: see :mod:`sim_slaves.ethercat.runner`."""

from sim_slaves.ethercat.runner import main

raise SystemExit(main())
