"""Run one measured Python step in this (fresh) process; used by ``common.run_step``.

    python bench/_worker.py MODULE:FUNCTION KWARGS_JSON RESULT_JSON [--import MOD ...]

Imports the ``--import`` modules and MODULE (untimed), records the resident size
(``baseline_mb``), times ``FUNCTION(**kwargs)`` and writes its returned dict, with
``time_s`` (unless the function set it) and ``baseline_mb``, to RESULT_JSON.
The parent reads this process's peak RSS from its own wait.
"""

from __future__ import annotations

import importlib
import json
import os
import resource
import sys
import time
from pathlib import Path

# the process as heartreg's command sets it up (heartreg/cli.py): numpy asks for no transparent huge pages
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


def main(argv: list[str]) -> int:
    target, payload, result_path, *rest = argv
    imports = [rest[i + 1] for i in range(len(rest) - 1) if rest[i] == "--import"]
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    for mod in imports:
        importlib.import_module(mod)
    module_name, func_name = target.split(":")
    fn = getattr(importlib.import_module(module_name), func_name)
    kwargs = json.loads(payload)
    baseline_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    t0 = time.perf_counter()
    result = fn(**kwargs) or {}
    elapsed = time.perf_counter() - t0
    result.setdefault("time_s", elapsed)
    result["baseline_mb"] = baseline_mb
    Path(result_path).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
