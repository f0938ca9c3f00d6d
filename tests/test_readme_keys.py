"""Every config key the README documents exists, takes the README's own value, and a
value of the wrong kind stops before any work with an error naming that key.

The keys are read from the README at test time (``key=value`` in its code), so a key
renamed in the code and not in the README, or a key the README adds, is covered
without touching this test.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from flowins.ins.imu_model import imu_model
from flowins.settings import evaluate_settings, navigation_config, parameter_sets, train_settings

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / "configs"
GROUPS = sorted(p.name for p in CONFIG_DIR.iterdir() if p.is_dir() and p.name != "hydra")
TOP = ("combinations", "quick", "plots", "progress", "flow_panels", "window_s", "methods", "seed", "cache_dir",
       "flow_pairs")
#: values in the README that stand for the user's own (a path, a folder)
PLACEHOLDER = re.compile(r"^(DIR\d?|PATH|FILE|OUT|.*\.\.\..*|\[name.*|outputs/.*|.*\.(yaml|ckpt|pth|tar)|/.*|\$.*|\[\{path.*)$")


def _code(text: str) -> list[str]:
    """The README's code: each line of a code block, each inline code span."""
    snippets = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S):
        snippets += block.splitlines()
    text = re.sub(r"```[a-z]*\n.*?```", "", text, flags=re.S)
    return snippets + [span.replace("\n", " ") for span in re.findall(r"`([^`]+)`", text)]


KEYS = "|".join(GROUPS + list(TOP))


def readme_commands() -> list[tuple[str, ...]]:
    """The overrides of each command in the README's code (an inline code span or one line
    of a code block), as ``key=value`` strings, the group choices (``flow=flownet2``) included."""
    pattern = re.compile(rf"(?<![\w./-])\+?((?:{KEYS})(?:\.[a-z_0-9]+)*)=(\[[^\]]*\]|'[^']*'|[^\s`|,);]+)")
    commands = set()
    for snippet in _code((ROOT / "README.md").read_text()):
        found = tuple(f"{k}={v.rstrip('.:').strip(chr(39))}" for k, v in pattern.findall(snippet))  # the shell's quotes
        if found:
            commands.add(found)
    return sorted(commands)


def readme_bare_keys() -> list[str]:
    """Dotted config keys the README names without a value (``model.nll_weight``)."""
    pattern = re.compile(rf"^((?:{KEYS})(?:\.[a-z_0-9]+)+)$")
    files = re.compile(r"\.(csv|yaml|py|json|tum|png|log|md|txt)$")
    return sorted({m.group(1) for snippet in _code((ROOT / "README.md").read_text())
                   if (m := pattern.match(snippet.strip())) and not files.search(m.group(1))})


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+")


def _value(override: str) -> str:
    return override.split("=", 1)[1]


def compose_config(overrides: list[str], key: str | None = None) -> tuple[str, dict]:
    """The first primary config (evaluate, then train) that takes ``overrides`` (and has ``key``)."""
    last = None
    for primary in ("evaluate", "train"):
        try:
            with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
                cfg = compose(config_name=primary, overrides=["output_dir=/tmp/unused", *overrides])
            cfg = OmegaConf.to_container(cfg, resolve=True)
            if key is None or _has(cfg, key):
                return primary, cfg
        except ConfigCompositionException as error:
            last = error
    raise AssertionError(f"{overrides} {key or ''}: no config takes it: {last}")


def _has(cfg: dict, key: str) -> bool:
    for part in key.split("."):
        if not isinstance(cfg, dict) or part not in cfg:
            return False
        cfg = cfg[part]
    return True


def validate(primary: str, cfg: dict) -> None:
    """What each job checks before its work; on a machine without CUDA a documented GPU
    setting (``flow.device=cuda``, ``filter.device=cuda``, ``trainer=gpu``) must stop with the
    refusal that says so."""
    needs_cuda = ("cuda" in (cfg["flow"].get("device"), cfg["filter"]["device"])
                  or cfg.get("trainer", {}).get("accelerator") == "gpu")
    if needs_cuda and not torch.cuda.is_available():
        with pytest.raises(ValueError, match="sees no CUDA GPU here"):
            _validate(primary, cfg)
    else:
        _validate(primary, cfg)


def _validate(primary: str, cfg: dict) -> None:
    recording = bool(cfg["sequence"].get("path"))
    if primary == "evaluate":
        evaluate_settings(cfg)
        navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=recording))
    else:
        train_settings(cfg)
        base = navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=recording))
        parameter_sets(cfg, base)


COMMANDS = readme_commands()
#: ``(key, the command it is documented in)`` for each leaf key (not a group choice)
LEAVES = sorted(({k: () for k in readme_bare_keys()} | {_key(o): command for command in COMMANDS for o in command
                                                           if "." in _key(o) or _key(o) in TOP}).items())


def _node(cfg: dict, key: str):
    for part in key.split("."):
        cfg = cfg[part]
    return cfg


def test_the_readme_documents_keys():
    assert len(COMMANDS) >= 20 and len(LEAVES) >= 20, COMMANDS  # the extraction found the README's commands


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_each_documented_command_composes_and_its_values_pass(command):
    primary, cfg = compose_config(list(command))
    if not any(PLACEHOLDER.match(_value(o)) for o in command):
        validate(primary, cfg)


#: a value no documented key takes: a list of lists (Hydra parses it; no key expects it)
WRONG = "[[7]]"


@pytest.mark.parametrize("key, command", LEAVES, ids=[k for k, _ in LEAVES])
def test_a_wrong_value_for_each_documented_key_names_the_key(key, command):
    context = [o for o in command if _key(o) != key and not PLACEHOLDER.match(_value(o))]
    primary, cfg = compose_config(context, key)
    if isinstance(_node(cfg, key), dict):  # a group of keys (filter.init): it exists, its leaves are tested
        return
    primary, cfg = compose_config([*context, f"{key}={WRONG}"])
    with pytest.raises(ValueError) as info:
        validate(primary, cfg)
    assert key in str(info.value), str(info.value)


def help_commands() -> list[tuple[str, ...]]:
    """The overrides each job's ``--help`` (``hydra.help.template``) shows, one line each."""
    pattern = re.compile(rf"(?<![\w./-])\+?((?:{KEYS})(?:\.[a-z_0-9]+)*)=(\[[^\]]*\]|[^\s`|,);]+)")
    out = []
    for primary in ("evaluate", "train"):
        template = OmegaConf.load(CONFIG_DIR / f"{primary}.yaml")["hydra"]["help"]["template"]
        assert len(template.splitlines()) <= 40, f"{primary} --help is {len(template.splitlines())} lines"
        out += [tuple(f"{k}={v}" for k, v in pattern.findall(line)) for line in template.splitlines()]
    return sorted({c for c in out if c})


@pytest.mark.parametrize("command", help_commands(), ids=" ".join)
def test_each_override_the_help_shows_composes_and_passes(command):
    primary, cfg = compose_config(list(command))
    if not any(PLACEHOLDER.match(_value(o)) for o in command):
        validate(primary, cfg)
