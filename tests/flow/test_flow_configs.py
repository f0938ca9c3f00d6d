"""configs/flow/*.yaml (dense providers) and configs/sparse/lk.yaml (the tracker): each composes,
names a real class, mirrors its defaults, and instantiates."""
import importlib
import inspect
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"
NAMES = ("dis", "lk", "spynet", "flownet2")


def flow_config(name: str, overrides: tuple[str, ...] = ()):
    if name == "lk":
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            return compose(config_name="sparse/lk", overrides=[f"sparse.tracker.{o}" for o in overrides]).sparse.tracker
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name=f"flow/{name}", overrides=[f"flow.{o}" for o in overrides]).flow


def target_class(cfg):
    """The class a config names: a target that does not import (a renamed class) fails."""
    module, _, name = cfg._target_.rpartition(".")
    cls = getattr(importlib.import_module(module), name, None)
    assert cls is not None, f"{cfg._target_}: {module} has no {name}"
    return cls


@pytest.mark.parametrize("name", NAMES)
def test_config_mirrors_constructor_defaults(name):
    cfg = flow_config(name)
    cls = target_class(cfg)
    params = inspect.signature(cls.__init__).parameters
    for key in cfg:
        if key == "_target_":
            continue
        assert key in params, f"configs/flow/{name}.yaml: {key} is not an argument of {cls.__name__}"
        if OmegaConf.is_missing(cfg, key):
            continue
        default = params[key].default
        if default is not inspect.Parameter.empty:
            assert cfg[key] == default, f"configs/flow/{name}.yaml: {key}={cfg[key]!r}, {cls.__name__} default {default!r}"


def test_dis_and_lk_instantiate():
    from flowins.flow.classical import DISProvider
    from flowins.flow.sparse import ShiTomasiLK

    dis = instantiate(flow_config("dis", ("preset=fast",)))
    assert isinstance(dis, DISProvider) and dis.preset == "fast" and dis.fb_gain == 2.0
    lk = instantiate(flow_config("lk"))
    assert isinstance(lk, ShiTomasiLK) and lk.max_corners == 300 and lk.levels == 3 and lk.win_size_px == 21


def test_spynet_defaults_as_the_paper():
    cfg = flow_config("spynet")
    assert cfg._target_ == "flowins.flow.spynet.SpyNetProvider" and cfg.mc_passes == 10 and cfg.p == 0.2


def test_flownet2_needs_a_checkpoint():
    cfg = flow_config("flownet2")
    assert cfg._target_ == "flowins.flow.flownet2.provider.FlowNet2Provider"
    assert cfg.dropout_option == 2 and cfg.p == 0.2 and cfg.passes == 10
    assert OmegaConf.is_missing(cfg, "checkpoint")
    target_class(cfg)  # skips if the class is not there yet
    with pytest.raises(Exception, match="checkpoint"):  # omegaconf: Missing mandatory value: checkpoint
        instantiate(cfg)
    with pytest.raises(Exception, match="no checkpoint given"):  # the provider's own message on null
        instantiate(flow_config("flownet2", ("checkpoint=null",)))
