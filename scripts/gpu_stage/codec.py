"""Lossless packing of a dataset split, to move it where only a small copy travels: float32
positions as int32 bit patterns, third differences in time (wrapping int32 arithmetic, so the
cumulative sums restore every bit), byte planes, xz. About 3.7x on the default scene.

    python scripts/gpu_stage/codec.py pack SPLIT.h5 OUT.xzd [N_FIRST]
    python scripts/gpu_stage/codec.py unpack SRC_DIR DST_DIR METADATA.json   # every SRC_DIR/*.xzd
"""
import json, lzma, shutil, sys
from pathlib import Path
import numpy as np

ORDER = 3

def pack(h5_path, out_path, limit=None):
    import h5py
    with h5py.File(h5_path, "r") as f:
        keys = sorted(f.keys())[:limit]
        shapes, types, chunks = [], [], []
        for k in keys:
            p = f[k]["position"][()]
            assert p.dtype == np.float32
            d = p.view(np.int32)
            for _ in range(ORDER):
                d = np.diff(d, axis=0, prepend=np.zeros_like(d[:1]))  # int32, wraps
            chunks.append(d.reshape(-1))
            shapes.append(list(p.shape))
            types.append(f[k]["particle_type"][()].astype(np.int64).tolist())
    flat = np.concatenate(chunks).astype(np.int32)
    planes = np.ascontiguousarray(flat.view(np.uint8).reshape(-1, 4).T).tobytes()
    header = json.dumps(dict(keys=keys, shapes=shapes, types=types)).encode()
    with open(out_path, "wb") as f:
        f.write(len(header).to_bytes(8, "little")); f.write(header); f.write(lzma.compress(planes, preset=6))

def unpack(path):
    raw = Path(path).read_bytes()
    n = int.from_bytes(raw[:8], "little"); head = json.loads(raw[8:8 + n])
    planes = np.frombuffer(lzma.decompress(raw[8 + n:]), dtype=np.uint8)
    flat = np.ascontiguousarray(planes.reshape(4, -1).T).view(np.int32).reshape(-1)
    out, at = [], 0
    for shape, types in zip(head["shapes"], head["types"]):
        size = int(np.prod(shape)); d = flat[at:at + size].reshape(shape); at += size
        for _ in range(ORDER):
            d = np.cumsum(d, axis=0, dtype=np.int32)
        out.append((d.view(np.float32), np.asarray(types, dtype=np.int64)))
    return head["keys"], out

if __name__ == "__main__":
    if sys.argv[1] == "pack":
        pack(sys.argv[2], sys.argv[3], int(sys.argv[4]) if len(sys.argv) > 4 else None)
    else:  # unpack SRC_DIR DST_DIR METADATA
        sys.path.insert(0, "src")
        from rgns.data.contract import write_split
        src, dst = Path(sys.argv[2]), Path(sys.argv[3]); dst.mkdir(parents=True, exist_ok=True)
        for part in sorted(src.glob("*.xzd")):
            _, trajs = unpack(part)
            write_split(dst / f"{part.stem}.h5", trajs)
            print(part.stem, len(trajs), flush=True)
        shutil.copyfile(sys.argv[4], dst / "metadata.json")
