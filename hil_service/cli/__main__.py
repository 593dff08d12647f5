import sys

from hil_service.cli import main

sys.exit(main())
