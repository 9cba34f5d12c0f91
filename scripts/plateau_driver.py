"""Plateau comparison driver (docs/benchmarks.md, "Error against time before and after issue 17"). Run the full suite's main runs (3dgs, dibrgs on four 256 scenes) one at a time with 1 thread,
with whichever dibrgs_core is first on sys.path; results as the runner writes them, plus wall time."""
import json
import sys
import time
from pathlib import Path

from dibrgs_core.bench import runner

work = Path(sys.argv[1])
results = work / "results" / "runs"
results.mkdir(parents=True, exist_ok=True)
import dibrgs_core
print("package", dibrgs_core.__file__, flush=True)
for kind in ("city", "mountain", "village", "stadium"):
    for m in ("3dgs", "dibrgs"):
        spec = runner.RunSpec(kind, 256, m)
        out = results / f"{spec.key}.json"
        if out.exists():
            continue
        t0 = time.time()
        res = runner.run_one(spec, work, None, threads=1)
        res["wall_seconds"] = time.time() - t0
        res["started"] = t0
        out.write_text(json.dumps(res))
        print(time.strftime("%H:%M:%S"), spec.key, res["row"]["psnr"], res["row"]["train_seconds"],
              res["wall_seconds"], flush=True)
