"""Staged training recipes: every stage of a preset from scratch, each from the previous one's checkpoint.

``python -m rgns.training.stages BENCHMARK MODEL [seed=N] [out=DIR] [run_dir=DIR] [overwrite=true]
[preset=NAME|FILE] [key=value ...]`` (``bash scripts/pretrain.sh`` is this; docs/pretrain_recipes.md).

A preset is ``conf/experiment/pretrain/<benchmark>_<model>.yaml``: a train.py experiment (what every
stage shares) with, under ``pretrain:``, the dataset it needs (``rgns.data.generate``'s arguments) and
its ``stages``, each a ``name``, a list of train.py ``overrides`` and a ``pick`` (``best``: the
checkpoint callback's best validation, or ``last``). Each stage runs as

    python train.py experiment=pretrain/<preset> <stage's overrides> seed=N <key=value ...>
        init_from=<previous stage's pick> hydra.run.dir=<run_dir>/<stage>

- The dataset is generated first when it is missing (not when a ``data.root=`` is given).
- A stage with ``done.json`` in its folder (written only after train.py ended with 0) is skipped; a
  stage started before (``stage.json``) that has ``checkpoints/last.ckpt`` but no ``done.json`` goes
  on from it (``resume=``). A folder whose stage ran with other overrides is refused, not mixed.
- SIGINT / SIGTERM: train.py finishes its step and saves ``last.ckpt``; the same command goes on.
- At the end the last stage's pick is copied to ``<out>/<model>.ckpt`` (through a temporary file
  renamed into place; ``out`` is by default ``pretrained/<preset>_rebuilt``, one folder per preset)
  with ``<model>.json``: the preset, each stage's overrides, pick, best validation score and step,
  the commit, and no path of one machine (stages are named, not located).
  An existing ``<model>.ckpt`` with other contents is kept unless ``overwrite=true``.

Checkpoints are read with ``torch.load(weights_only=True)`` only, their configs checked against
rgns's own targets (:mod:`rgns.targets`).
"""
from __future__ import annotations

import hashlib
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from omegaconf import OmegaConf

from rgns import config_dir
from rgns.data.contract import atomic_path
from rgns.training.module import _read_checkpoint

OPTIONS = ("preset", "out", "run_dir", "overwrite", "seed")
USAGE = ("usage: python -m rgns.training.stages BENCHMARK MODEL [seed=N] [out=DIR] [run_dir=DIR] "
         "[overwrite=true] [preset=NAME|FILE.yaml] [key=value ...]\n"
         "  e.g. bash scripts/pretrain.sh waterdrop rgns trainer.max_steps=20 trainer.val_check_interval=20  (a smoke run)")


class RecipeError(RuntimeError):
    """A recipe that cannot run as asked; the message says why and what to do."""


def say(message: str) -> None:
    print(f"[pretrain] {message}", flush=True)


# ---------------------------------------------------------------------------------------- presets

def find_preset(preset: str) -> tuple[Path, str, Path | None]:
    """The preset file, its experiment name (``pretrain/waterdrop_rgns``) and the config folder to add
    to train.py's search path (None: the package's own). ``preset``: a name under
    ``experiment/pretrain/`` of the package's configs, or a YAML file under a folder ``experiment/``."""
    if not preset.endswith((".yaml", ".yml")):
        path = config_dir() / "experiment" / "pretrain" / f"{preset}.yaml"
        if not path.is_file():
            known = sorted(p.stem for p in (config_dir() / "experiment" / "pretrain").glob("*.yaml"))
            raise RecipeError(f"no preset {preset!r} (conf/experiment/pretrain/{preset}.yaml); presets: {known}")
        return path, f"pretrain/{preset}", None
    path = Path(preset)
    if not path.is_file():
        raise RecipeError(f"{preset}: no such preset file")
    parts = path.resolve().parts
    if "experiment" not in parts[:-1]:
        raise RecipeError(f"{preset}: a preset file lies under a folder named experiment/ (its parent is added "
                          "to train.py's config search path, so experiment=<name> finds it)")
    at = len(parts) - 1 - parts[::-1].index("experiment")
    root = Path(*parts[:at])
    name = "/".join(parts[at + 1:])
    return path, name.rsplit(".", 1)[0], root


def read_preset(path: Path) -> dict:
    spec = OmegaConf.to_container(OmegaConf.load(path), resolve=False).get("pretrain")
    if not isinstance(spec, dict) or not spec.get("stages"):
        raise RecipeError(f"{path}: no pretrain.stages (a list of {{name, overrides, pick}})")
    names = []
    for stage in spec["stages"]:
        if not isinstance(stage, dict) or not isinstance(stage.get("name"), str) or "/" in stage["name"]:
            raise RecipeError(f"{path}: each stage needs a plain name (a folder name): {stage}")
        stage.setdefault("overrides", [])
        stage.setdefault("pick", "best")
        if stage["pick"] not in ("best", "last"):
            raise RecipeError(f"{path}: stage {stage['name']}: pick is best or last, not {stage['pick']!r}")
        names.append(stage["name"])
    if len(set(names)) != len(names):
        raise RecipeError(f"{path}: stage names repeat: {names}")
    return spec


# ------------------------------------------------------------------------------------ processes

def run_logged(command: list[str], log: Path | None) -> int:
    """Run ``command``, its output to the terminal and appended to ``log``. A SIGTERM to this
    process is passed on (train.py then saves and exits 143); Ctrl-C reaches the child from the
    terminal, so here it only waits for the child to finish saving."""
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)

    def forward(signum, frame):
        try:
            process.send_signal(signum)
        except ProcessLookupError:
            pass

    # a Python handler, not SIG_IGN: the child must not inherit an ignored SIGINT
    previous = {signal.SIGINT: signal.signal(signal.SIGINT, lambda s, f: None),
                signal.SIGTERM: signal.signal(signal.SIGTERM, forward)}
    try:
        with open(log, "a") if log else open(os.devnull, "w") as out:
            for line in process.stdout:
                out.write(line)
                out.flush()
                sys.stdout.write(line)
                sys.stdout.flush()
        return process.wait()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def train_script() -> Path:
    """The repository's train.py (beside src/), else the one in the working folder."""
    beside = Path(__file__).resolve().parents[3] / "train.py"
    return beside if beside.is_file() else Path("train.py").resolve()


def write_json(path: Path, payload: dict) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(payload, indent=2) + "\n")


def read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise RecipeError(f"{path}: unreadable ({err}); delete it to run its stage again") from None


def commit() -> tuple[str | None, bool | None]:
    """``git rev-parse HEAD`` here and whether tracked files differ from it; (None, None) outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=30)
        if head.returncode != 0:
            return None, None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, timeout=60)
        return head.stdout.strip(), bool(dirty.stdout.strip()) if dirty.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None, None


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def portable(override: str) -> str:
    """An override as the provenance records it: an absolute path's folders left out."""
    key, sep, value = override.partition("=")
    if sep and (value.startswith(("/", "~")) or (len(value) > 2 and value[1] == ":" and value[2] in "\\/")):
        return f"{key}=<local>/{Path(value).name}"
    return override


# --------------------------------------------------------------------------------------- stages

def stage_result(folder: Path, pick: str) -> dict:
    """What a finished stage left: the picked checkpoint (a name under checkpoints/), its step, and
    the best score its checkpoint callback recorded (from last.ckpt's callback state)."""
    checkpoints = folder / "checkpoints"
    last = checkpoints / "last.ckpt"
    if not last.is_file():
        raise RecipeError(f"{folder}: train.py ended without {last}")
    state = _read_checkpoint(str(last), "stage checkpoint")
    monitored = [s for key, s in (state.get("callbacks") or {}).items()
                 if key.startswith("ModelCheckpoint") and isinstance(s, dict) and s.get("monitor")]
    best = next((s for s in monitored if s.get("best_model_path")), None)
    score = best.get("best_model_score") if best else None
    score = None if score is None else float(score)
    name = "last.ckpt"
    if pick == "best":
        if best is not None and (checkpoints / Path(best["best_model_path"]).name).is_file():
            name = Path(best["best_model_path"]).name
        else:
            say(f"{folder.name}: no best checkpoint recorded (no validation?): its last.ckpt goes on")
    chosen = state if name == "last.ckpt" else _read_checkpoint(str(checkpoints / name), "stage checkpoint")
    return {"checkpoint": f"checkpoints/{name}", "global_step": int(chosen.get("global_step", 0)),
            "last_step": int(state.get("global_step", 0)),
            "monitor": best.get("monitor") if best else (monitored[0]["monitor"] if monitored else None),
            "best_score": score}


def default_out(preset_path: Path) -> Path:
    """Where a recipe's result goes without ``out=``: ``pretrained/<preset>_rebuilt``, one folder per
    preset (``waterdrop_gns`` and ``waterdrop_gns_stride4`` do not share one)."""
    return Path("pretrained") / f"{preset_path.stem}_rebuilt"


def run_recipe(benchmark: str | None, model: str | None, options: dict, extras: list[str]) -> int:
    preset_name = options.get("preset") or f"{benchmark}_{model}"
    preset_path, experiment, search_root = find_preset(preset_name)
    spec = read_preset(preset_path)
    benchmark = benchmark or spec.get("benchmark") or "recipe"
    model = model or spec.get("model") or preset_path.stem
    seed = int(options.get("seed", 0))
    run_dir = Path(options.get("run_dir") or f"outputs/pretrain/{preset_path.stem}_seed{seed}")
    out = Path(options.get("out") or default_out(preset_path))
    overwrite = str(options.get("overwrite", "false")).lower() in ("true", "1", "yes")
    final, final_json = out / f"{model}.ckpt", out / f"{model}.json"
    stages = spec["stages"]
    train = train_script()
    head = [sys.executable, str(train)] + ([f"--config-dir={search_root}"] if search_root else [])
    common = [f"experiment={experiment}"]

    def done(stage) -> dict | None:
        marker = run_dir / stage["name"] / "done.json"
        return read_json(marker) if marker.is_file() else None

    if final.exists() and not overwrite:
        results = [done(s) for s in stages]
        last = results[-1]
        if not (all(results) and sha256(run_dir / stages[-1]["name"] / last["checkpoint"]) == sha256(final)):
            raise RecipeError(f"{final} exists (another run's file): not overwritten; give out=<another folder> "
                              "or overwrite=true")

    say(f"preset {preset_path.name}: {len(stages)} stages ({', '.join(s['name'] for s in stages)}), seed {seed}; "
        f"run folders under {run_dir}/, result {final}")
    dataset = spec.get("dataset")
    if dataset and not any(e.startswith(("data.root=", "data=")) for e in extras):
        out_dir = next((a.split("=", 1)[1] for a in dataset if a.startswith("out_dir=")), None)
        if out_dir is None or not (Path(out_dir) / "metadata.json").is_file():
            say(f"dataset: python -m rgns.data.generate {' '.join(dataset)}")
            rc = run_logged([sys.executable, "-m", "rgns.data.generate", *dataset], None)
            if rc != 0:
                say(f"the dataset's generation stopped (exit {rc}); the same command goes on with it")
                return rc

    previous = None  # (stage name, its picked checkpoint's path)
    records = []
    for number, stage in enumerate(stages, 1):
        folder = run_dir / stage["name"]
        overrides = [*common, *stage["overrides"], f"seed={seed}", *extras]
        chain = [f"init_from={previous[1]}"] if previous else []
        what = {"overrides": overrides, "init_from_stage": previous[0] if previous else None,
                "init_from_checkpoint": Path(previous[1]).name if previous else None}
        started = folder / "stage.json"
        result = done(stage)
        if started.is_file():
            before = read_json(started)
            if {k: before.get(k) for k in what} != what:
                raise RecipeError(f"{folder} holds this stage run with other settings ({before.get('overrides')}, "
                                  f"from {before.get('init_from_stage')}'s {before.get('init_from_checkpoint')}); "
                                  f"not mixed with these ({overrides}): give run_dir=<another folder> or delete it")
        elif result is not None:
            raise RecipeError(f"{folder}: done.json without stage.json; delete the folder to run the stage again")
        if result is not None:
            say(f"stage {number}/{len(stages)} {stage['name']}: done ({result['checkpoint']}, step "
                f"{result['global_step']}, {result['monitor']} {result['best_score']}): skipped")
        else:
            folder.mkdir(parents=True, exist_ok=True)
            last = folder / "checkpoints" / "last.ckpt"
            wall = read_json(started).get("wall_s", 0.0) if started.is_file() else 0.0
            sessions = read_json(started).get("sessions", 0) if started.is_file() else 0
            if started.is_file() and last.is_file():
                tail = ["init_from=null", f"resume={last}"]
                how = f"goes on from {last}"
            else:
                tail = chain
                how = f"from {previous[0]}'s {Path(previous[1]).name}" if previous else "from scratch"
            write_json(started, {**what, "wall_s": wall, "sessions": sessions + 1})
            command = [*head, *overrides, *tail, f"hydra.run.dir={folder}"]
            log = folder / "output.log"
            say(f"stage {number}/{len(stages)} {stage['name']}: {how}; log {log}")
            say("  " + shlex.join(["python", os.path.relpath(train), *command[2:]]))
            start = time.time()
            rc = run_logged(command, log)
            wall += time.time() - start
            write_json(started, {**what, "wall_s": round(wall, 1), "sessions": sessions + 1})
            if rc != 0:
                say(f"stage {stage['name']} stopped (exit {rc}; log {log}). The same command goes on from its "
                    "last checkpoint")
                return rc
            result = {**stage_result(folder, stage["pick"]), "pick": stage["pick"], "wall_s": round(wall, 1),
                      "sessions": sessions + 1}
            write_json(folder / "done.json", {**what, **result})
            say(f"stage {number}/{len(stages)} {stage['name']}: done in {wall:.0f} s ({result['checkpoint']}, step "
                f"{result['global_step']}, {result['monitor']} {result['best_score']})")
        previous = (stage["name"], str(folder / result["checkpoint"]))
        records.append({"name": stage["name"], "overrides": list(stage["overrides"]),
                        "init_from": f"{what['init_from_stage']}: {what['init_from_checkpoint']}"
                        if what["init_from_stage"] else None,
                        "pick": stage["pick"], "checkpoint": Path(result["checkpoint"]).name,
                        "global_step": result["global_step"], "monitor": result["monitor"],
                        "best_score": result["best_score"], "wall_s": result.get("wall_s")})

    source = Path(previous[1])
    if final.exists() and sha256(final) == sha256(source) and final_json.exists():
        say(f"{final}: already this recipe's result; nothing to write")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(final) as tmp:
        shutil.copyfile(source, tmp)
    head_commit, dirty = commit()
    user = [portable(e) for e in extras]
    builtin = search_root is None
    last_record = records[-1]
    write_json(final_json, {
        "made_by": "rgns.training.stages (scripts/pretrain.sh): every stage of the preset from scratch",
        "command": shlex.join(["bash", "scripts/pretrain.sh", benchmark, model, f"seed={seed}",
                               *([portable(f"preset={options['preset']}")] if options.get("preset") else []), *user]),
        "preset": f"conf/experiment/pretrain/{preset_path.name}" if builtin else preset_path.name,
        "experiment": experiment,
        "benchmark": benchmark,
        "model": model,
        "seed": seed,
        "overrides": user,
        "dataset": f"python -m rgns.data.generate {' '.join(dataset)}" if dataset else None,
        "stages": records,
        "commit": head_commit,
        "commit_dirty": dirty,
        "monitor": last_record["monitor"],
        "best_score": last_record["best_score"],
        "global_step": last_record["global_step"],
        "wall_s": round(sum(r["wall_s"] or 0.0 for r in records), 1),
        "sha256": sha256(final),
    })
    say(f"wrote {final} ({records[-1]['name']}'s {records[-1]['checkpoint']}) and {final_json}")
    return 0


def parse(argv: list[str]) -> tuple[str | None, str | None, dict, list[str]]:
    positional = [a for a in argv if "=" not in a]
    options, extras = {}, []
    for a in argv:
        if "=" in a:
            key = a.split("=", 1)[0]
            (options.__setitem__(key, a.split("=", 1)[1]) if key in OPTIONS else extras.append(a))
    if any(a in ("-h", "--help") for a in positional):
        raise SystemExit(USAGE)
    if len(positional) == 2:
        return positional[0], positional[1], options, extras
    if not positional and options.get("preset"):
        return None, None, options, extras
    raise RecipeError(f"give BENCHMARK MODEL (got {positional})")


def main(argv: list[str] | None = None) -> int:
    try:
        benchmark, model, options, extras = parse(sys.argv[1:] if argv is None else argv)
        return run_recipe(benchmark, model, options, extras)
    except RecipeError as err:
        print(f"[pretrain] error: {err}\n{USAGE}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
