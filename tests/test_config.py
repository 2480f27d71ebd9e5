"""Config tier: every group option composes and instantiates."""
from __future__ import annotations

import lightning as L
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from rgns import config_dir
from rgns.data.contract import read_metadata
from rgns.models import DMCF, EGNN, GNS, RGNS, NeuralSPH, SepGNS
from rgns.training.losses import LossDesign

CONF = config_dir()


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def train_cfg(tmp_path, *overrides):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("train", overrides=[f"output_dir={tmp_path}", *overrides])


def build_module(cfg, metadata):
    return instantiate(cfg.module, model=cfg.model, loss=cfg.loss, metadata=metadata, _recursive_=False)


def test_every_group_has_its_options():
    assert options("model") == ["dmcf", "egnn", "gns", "neural_sph", "rgns", "rgns_forward_only", "sep_gns"]
    assert options("loss") == ["dl1", "dl2", "dl3", "dl4"]
    assert options("trainer") == ["cpu", "ddp", "ddp_sim", "default", "gpu"]


@pytest.mark.parametrize(
    "model, cls, bidirectional_training",
    [("rgns", RGNS, True), ("rgns_forward_only", RGNS, False), ("gns", GNS, False), ("sep_gns", SepGNS, True),
     ("egnn", EGNN, False), ("neural_sph", NeuralSPH, False), ("dmcf", DMCF, False)],
)
def test_every_model_instantiates(tmp_path, tiny_dataset, model, cls, bidirectional_training):
    cfg = train_cfg(tmp_path, f"model={model}", "model.latent=16", "model.layers=2")
    module = build_module(cfg, read_metadata(tiny_dataset))
    assert type(module.model) is cls
    assert module.train_inverse is bidirectional_training
    assert module.model.history == cfg.history == 5


@pytest.mark.parametrize("encoder", ["ilp", "mlp"])
@pytest.mark.parametrize("edges", ["fixed", "updated"])
def test_ablation_options_reach_the_model(tmp_path, tiny_dataset, encoder, edges):
    cfg = train_cfg(tmp_path, f"model.encoder={encoder}", f"model.edges={edges}", "model.latent=16", "model.layers=2")
    module = build_module(cfg, read_metadata(tiny_dataset))
    assert module.hparams.model["encoder"] == encoder and module.hparams.model["edges"] == edges
    sizes = {}
    for variant in ("ilp", "mlp"):
        c = train_cfg(tmp_path, f"model.encoder={variant}", f"model.edges={edges}", "model.latent=16", "model.layers=2")
        sizes[variant] = sum(p.numel() for p in build_module(c, read_metadata(tiny_dataset)).parameters())
    assert sizes["ilp"] != sizes["mlp"]  # the option really changes the network


@pytest.mark.parametrize("loss, cosine, mmd", [("dl1", 0, 1), ("dl2", 1, 1), ("dl3", 1, 0), ("dl4", 0, 0)])
def test_loss_designs(tmp_path, loss, cosine, mmd):
    design = instantiate(train_cfg(tmp_path, f"loss={loss}").loss)
    assert isinstance(design, LossDesign) and design.name == loss.upper()
    assert design.mse == 1.0 and bool(design.cosine) == bool(cosine) and bool(design.mmd) == bool(mmd)


@pytest.mark.parametrize("trainer", ["cpu", "default", "ddp_sim"])
def test_cpu_trainers_instantiate(tmp_path, trainer):
    cfg = train_cfg(tmp_path, f"trainer={trainer}")
    built = instantiate(cfg.trainer, logger=instantiate(cfg.logger), enable_progress_bar=False)
    assert isinstance(built, L.Trainer)
    assert built.world_size == (2 if trainer == "ddp_sim" else 1)
    assert isinstance(built.logger, L.pytorch.loggers.TensorBoardLogger)
    if trainer == "ddp_sim":  # a bounded wait for a rank that never comes (torch's default: 30 minutes)
        assert isinstance(built.strategy, L.pytorch.strategies.DDPStrategy)
        assert built.strategy._timeout.total_seconds() == 600


def test_gpu_trainers_ask_for_gpus(tmp_path):
    ddp = train_cfg(tmp_path, "trainer=ddp").trainer
    assert (ddp.accelerator, ddp.strategy._target_, ddp.devices) == ("gpu", "rgns.training.ddp.ddp_strategy", -1)
    assert train_cfg(tmp_path, "trainer=gpu").trainer.accelerator == "gpu"


def test_main_experiment_patches_only_its_deltas(tmp_path):
    cfg = train_cfg(tmp_path, "experiment=main")
    assert cfg.trainer.accelerator == "cpu"
    assert (cfg.model.latent, cfg.model.layers) == (32, 2)
    assert cfg.model._target_ == "rgns.models.RGNS"
    assert train_cfg(tmp_path, "experiment=main", "model=gns").model._target_ == "rgns.models.GNS"


def test_default_data_makes_itself(tmp_path):
    cfg = train_cfg(tmp_path, f"data.root={tmp_path / 'data'}")
    datamodule = instantiate(cfg.data)
    assert datamodule.make is not None and datamodule.make.keywords["scene"] == "waterdrop"


def main_job_runs() -> list[list[str]]:
    """The train.py overrides of each run of scripts/main.sh, read from the script itself: the
    ``train FOLDER MODEL STEPS CAP ...`` runs and the ``stage MODEL PICK ...`` runs (``stage``'s own
    steps, cap and experiment), with the script's override arrays (``rgns=(...)``) expanded."""
    import re
    import shlex
    from pathlib import Path

    script = (Path(__file__).parents[1] / "scripts" / "main.sh").read_text()
    arrays = {name: shlex.split(body) for name, body in re.findall(r"^(\w+)=\(([^)]*)\)", script, re.M)}

    def expand(extra: str) -> list[str]:
        return [o for token in shlex.split(extra) for o in arrays.get(token.removeprefix("${").removesuffix("[@]}"),
                                                                       [token])]

    def run(experiment, model, steps, cap, extra):
        return [f"experiment={experiment}", f"model={model}", f"trainer.max_steps={steps}", f"trainer.max_time={cap}",
                "trainer.enable_progress_bar=false", *expand(extra)]

    assert 'train.py experiment="$experiment" model="$model" trainer.max_steps="$steps" trainer.max_time="$cap"' in script
    runs = [run("main", model, steps, cap, extra) for model, steps, cap, extra in
            re.findall(r'train \w+ (\w+) (\d+) (\S+) ((?:(?:[\w.]+=\S+|"\$\{\w+\[@\]\}") )*)"\$@"', script)]
    steps, cap, experiment = re.search(r'train train "\$model" (\d+) (\S+) experiment=(\w+)', script).groups()
    runs += [run(experiment, model, steps, cap, extra) for model, extra in
             re.findall(r'stage (\w+) (?:best|last) ((?:"\$\{\w+\[@\]\}" )*)"\$@"', script)]
    return runs


def test_main_job_runs_compose_and_instantiate(tmp_path, tiny_dataset):
    """Every training run of scripts/main.sh composes with the overrides the script passes."""
    runs = main_job_runs()
    assert sorted(r[1] for r in runs) == ["model=gns", "model=gns", "model=rgns", "model=rgns", "model=sep_gns"]
    assert sum(r[0] == "experiment=main_stage" for r in runs) == 2  # R-GNS's and GNS's second stage
    for overrides in runs:
        cfg = train_cfg(tmp_path, *overrides, f"data.root={tiny_dataset}", "data.make=null")
        assert cfg.trainer.enable_progress_bar is False and cfg.model.hard_walls is True
        trainer = instantiate(cfg.trainer, logger=False, callbacks=[])
        assert trainer.max_steps == int(overrides[2].split("=")[1])
        # the evaluated checkpoint is chosen at validations: steps after the last one would never count
        assert trainer.max_steps % cfg.trainer.val_check_interval == 0, overrides
        build_module(cfg, read_metadata(tiny_dataset))


def test_training_benchmark_measures_the_main_jobs_models():
    """`python -m rgns.bench training --main` times each model with scripts/main.sh's model overrides."""
    from rgns.bench.training import MAIN_OVERRIDES

    for overrides in main_job_runs():
        model = overrides[1].split("=")[1]
        assert MAIN_OVERRIDES[model] == [o for o in overrides[5:] if o.startswith("model.")], model


@pytest.mark.parametrize("script", ["main.sh", "baselines.sh", "ablation.sh"])
def test_job_scripts_refuse_a_benchmark_they_have_no_scene_for(script):
    """`bash scripts/<job>.sh BENCHMARK` names the scenes it knows and stops before any set-up."""
    import subprocess
    from pathlib import Path

    path = Path(__file__).parents[1] / "scripts" / script
    for name in ("waterdrops", "water3d_full"):
        done = subprocess.run(["bash", str(path), name], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2, done.stderr
        assert f"scripts/{script}: no benchmark '{name}'" in done.stderr
        assert "waterramps" in done.stderr and "water3d " in done.stderr


@pytest.mark.parametrize("benchmark,dim", [("waterdrop", 2), ("waterramps", 2), ("water3d", 3), ("sand", 2)])
def test_main_job_trains_each_benchmark_on_its_own_scene(tmp_path, benchmark, dim):
    """With the data overrides scripts/main.sh gives every run, the DataModule reads and makes the
    benchmark's own dataset from the benchmark's own scene."""
    from pathlib import Path

    from rgns.data.generate import scene_config

    assert 'data.root="$data" data.make_root="$data" data.make.scene="$benchmark"' in (
        Path(__file__).parents[1] / "scripts" / "main.sh").read_text()
    data = tmp_path / f"{benchmark}40_main"
    cfg = train_cfg(tmp_path, "experiment=main", f"data.root={data}", f"data.make_root={data}",
                    f"data.make.scene={benchmark}")
    datamodule = instantiate(cfg.data)
    assert Path(datamodule.root) == data and datamodule.make is not None
    scene = scene_config(datamodule.make.keywords["scene"])
    assert scene["name"] == benchmark and scene["dim"] == dim
