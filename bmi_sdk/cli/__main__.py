import sys

from bmi_sdk.cli import main

sys.exit(main())
