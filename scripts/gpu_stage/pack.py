"""Pack the runs' checkpoints (optimizer state dropped) and logs into at most 6 tars under 15 MB."""
import io, re, sys, tarfile, torch
from pathlib import Path
src, out = Path(sys.argv[1]), Path(sys.argv[2])
logs = tarfile.open(out / "logs.tar.gz", "w:gz")
for run in sorted(p for p in src.iterdir() if p.is_dir()):
    for f in [src / f"{run.name}.log", *run.glob("*.json"), *run.glob("*.log"), *run.glob("*.yaml"), *run.glob(".hydra/*.yaml")]:
        if f.exists(): logs.add(f, arcname=f"{run.name}/{f.name}" if f.parent != src else f.name)
logs.close()
items = []
for ck in sorted(src.glob("*/checkpoints/*.ckpt")):
    c = torch.load(ck, map_location="cpu", weights_only=False); c.pop("optimizer_states", None)
    b = io.BytesIO(); torch.save(c, b); items.append((f"{ck.parts[-3]}/{ck.name}", b.getvalue()))
budget = 58e6
items.sort(key=lambda x: (int(m.group(1)) if (m := re.search(r"step(\d+)", x[0])) else 10**9), reverse=True)
kept, total = [], 0
for name, data in items:  # newest steps first; drop the earliest if over budget
    if total + len(data) <= budget: kept.append((name, data)); total += len(data)
    else: print("left out", name)
kept.sort()
groups, cur, size = [], [], 0
for name, data in kept:
    if cur and size + len(data) > 15e6:
        groups.append(cur); cur, size = [], 0
    cur.append((name, data)); size += len(data)
if cur: groups.append(cur)
assert len(groups) <= 6, len(groups)
for i, g in enumerate(groups):
    with tarfile.open(out / f"ckpts{i}.tar", "w") as t:
        for name, data in g:
            info = tarfile.TarInfo(name); info.size = len(data); t.addfile(info, io.BytesIO(data))
    print(f"ckpts{i}.tar", len(g), sum(len(d) for _, d in g) / 1e6, "MB")
