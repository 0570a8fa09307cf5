"""The prepared GPU check (``mvtn_exp/bench/device_check.py``): run it first on every lent GPU.

    python scripts/device_check.py "$OUT"            # at most 7 minutes on one H100 / H200
    python scripts/device_check.py OUT --dry-run     # tiny sizes on the CPU (the test suite's run)

Writes only ``device_check.md`` and ``device_check.json`` into the folder.
"""
import sys

from mvtn_exp.bench.device_check import main

if __name__ == "__main__":
    sys.exit(main())
