import sys

from valve_emulator.cli import main

sys.exit(main())
