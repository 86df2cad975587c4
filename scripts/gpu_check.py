"""The GPU check under the path the device machine's instructions name: ``frugalnerf-bench gpu-check``
(``frugalnerf_ns/bench/gpu_check.py``), same options, same exit code.

  python scripts/gpu_check.py [--dry-run] [--parts ...] [--out outputs/gpu_check]
"""

import sys

from frugalnerf_ns.bench.cli import main

if __name__ == "__main__":
    sys.exit(main(["gpu-check", *sys.argv[1:]]))
