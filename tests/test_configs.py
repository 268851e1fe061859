"""Every Hydra option file composes and maps 1:1 onto its target's keyword arguments."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_object
from omegaconf import OmegaConf

CONF = Path(__file__).resolve().parents[1] / "conf"
PRIMARY = sorted(p.stem for p in CONF.glob("*.yaml"))
OPTION_FILES = sorted(p for p in CONF.glob("*/*.yaml") if p.parent.name not in ("hydra", "experiment", "paths", "local"))


@pytest.mark.parametrize("path", OPTION_FILES, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_option_keys_are_target_kwargs(path):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=path.parent.name + "/" + path.stem)
    node = OmegaConf.to_container(cfg, resolve=False)
    node = node[path.parent.name] if path.parent.name in node else node
    assert "_target_" in node, f"{path} has no _target_"
    target = get_object(node["_target_"])
    params = inspect.signature(target).parameters
    keys = {k for k in node if not k.startswith("_")}
    accepts_kwargs = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    unknown = keys - set(params)
    assert accepts_kwargs or not unknown, f"{path}: keys {sorted(unknown)} are not kwargs of {node['_target_']}"


@pytest.mark.parametrize("name", PRIMARY)
def test_primary_configs_compose_with_integer_seed(name):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=name)
    assert isinstance(cfg.seed, int)
    assert cfg.experiment == name
