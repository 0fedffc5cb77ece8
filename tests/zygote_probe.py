"""What a command sees of its process, as JSON; exits with ``argv[1]`` (tests/test_zygote.py)."""

import json
import os
import sys

import torch

print(
    json.dumps(
        {
            "argv": sys.argv[1:],
            "cwd": os.getcwd(),
            "name": __name__,
            "path0": sys.path[0],
            "probe": os.environ.get("GC_PROBE"),
            "threads": torch.get_num_threads(),  # OpenMP read OMP_NUM_THREADS as torch loaded
        }
    )
)
sys.stderr.write("to stderr\n")
code = sys.argv[1]
if code == "raise":
    raise RuntimeError("the probe raised")
if code == "sleep":
    import time

    time.sleep(60)
sys.exit(int(code))
