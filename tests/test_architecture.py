"""The code's own rules, checked on the source: short functions, declared contracts, no branch on a mode name,
configs that reject what cannot work, presets that inherit instead of copying."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
import yaml

from lrslam.errors import InputError
from lrslam.pipeline.config import build_config, list_presets

ROOT = Path(__file__).resolve().parents[1]
SLAM_PACKAGES = ("pipeline", "backend", "frontend", "field", "core", "datasets", "evaluation", "tools", "cli")
MAX_BODY_LINES = 50


def _modules(*packages: str):
    for pkg in packages:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            yield path, ast.parse(path.read_text(), filename=str(path))


def _body_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the first statement after the docstring to the end of the function."""
    body = fn.body
    if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
            and isinstance(body[0].value.value, str):
        body = body[1:]
    return 0 if not body else fn.end_lineno - body[0].lineno + 1


def _is_numba_kernel(fn: ast.FunctionDef) -> bool:
    return any("njit" in ast.unparse(d) or "numba" in ast.unparse(d) for d in fn.decorator_list)


def test_no_function_body_over_50_lines():
    long = []
    for path, tree in _modules(*SLAM_PACKAGES):
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not _is_numba_kernel(node):
                n = _body_lines(node)
                if n > MAX_BODY_LINES:
                    long.append(f"{path.relative_to(ROOT)}::{node.name} ({n})")
    assert not long, "function bodies over 50 lines: " + ", ".join(long)


def test_body_line_counter_counts_what_it_should():
    fn = ast.parse('def f():\n    """doc\n    more"""\n    a = 1\n\n    return a\n').body[0]
    assert _body_lines(fn) == 3


def test_parts_are_typed_by_their_protocols_and_never_probed():
    """``Parts`` fields name protocols (never ``object``); the loop never asks a part what it is."""
    from dataclasses import fields

    from lrslam.pipeline import contracts
    from lrslam.pipeline.parts import Parts

    types = {f.name: str(f.type) for f in fields(Parts)}
    assert types == {"seeder": "Seeder", "keyframer": "Keyframer", "refiner": "Refiner | None",
                     "mapper": "Mapper | None", "backend": "Backend | None", "fusion": "Fusion | None"}
    for name in ("Seeder", "Keyframer", "Refiner", "Mapper", "Backend"):
        assert getattr(contracts, name)._is_protocol, name
    for path, tree in _modules("pipeline", "backend"):
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr"):
                target = ast.unparse(node.args[0])
                assert "part" not in target and "seeder" not in target and "mapper" not in target, \
                    f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}"


def test_nothing_branches_on_a_mode_name():
    """The mode is a name for a set of parts: only the preset table (and the config builder that applies it) may
    compare it with a mode name."""
    modes = {"field", "frontend", "fused"}
    hits = []
    for path, tree in _modules(*SLAM_PACKAGES):
        if path == ROOT / "pipeline" / "config.py":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Compare):
                consts = [c.value for c in [node.left, *node.comparators] if isinstance(c, ast.Constant)]
                consts += [e.value for c in node.comparators if isinstance(c, (ast.Tuple, ast.List, ast.Set))
                           for e in c.elts if isinstance(e, ast.Constant)]
                text = ast.unparse(node)
                names = [ast.unparse(c) for c in [node.left, *node.comparators] if isinstance(c, (ast.Name, ast.Attribute))]
                if any(n.split(".")[-1].endswith("mode") for n in names) and modes & {c for c in consts if isinstance(c, str)}:
                    hits.append(f"{path.relative_to(ROOT)}:{node.lineno}: {text}")
    assert not hits, hits


@pytest.mark.parametrize("overrides, keys", [
    (["graph.optimiser=isam2"], ("graph.optimiser", "parts.backend")),
    (["parts.seeder=constant_velocity"], ("backend.factors", "parts.seeder")),
    (["parts.refiner=none"], ("backend.factors", "parts.refiner")),
])
def test_combinations_that_cannot_work_are_rejected_when_the_config_is_built(overrides, keys):
    with pytest.raises(InputError) as e:
        build_config(mode="fused", overrides=overrides)
    msg = str(e.value)
    assert "\n" not in msg and all(k in msg for k in keys), msg
    # each works once the other key agrees
    fixes = {"graph.optimiser=isam2": "parts.backend=none", "parts.seeder=constant_velocity": 'backend.factors=["field","loop"]',
             "parts.refiner=none": 'backend.factors=["odometry","loop"]'}
    build_config(mode="fused", overrides=overrides + [fixes[overrides[0]]])


def test_a_rejected_combination_is_a_one_line_error_with_exit_2(tmp_path, capsys):
    from lrslam.cli import main

    with pytest.raises(SystemExit) as e:
        main(["run", "--demo", "--out", str(tmp_path / "r"), "--set", "graph.optimiser=isam2"])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and err.count("\n") == 0 and "graph.optimiser" in err and "parts.backend" in err


def test_one_keyframe_knob_for_both_keyframers():
    from lrslam.pipeline.parts import build_parts

    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    bound = np.array([[-2.0, 2.0], [-2.0, 2.0], [-1.0, 3.0]])
    field = build_parts(build_config(mode="field", overrides=["field.device=cpu", "keyframes.every_n=7"]), K, 48, 64,
                        bound)
    fused = build_parts(build_config(mode="fused", overrides=["field.device=cpu", "keyframes.every_n=7"]), K, 48, 64,
                        bound)
    assert field.keyframer.n == 7 and fused.keyframer.policy.cfg.every_n == 7
    assert build_config("tum", mode="field").keyframes.every_n == 1      # ESLAM TUM: every frame
    assert build_config("tum", mode="fused").keyframes.every_n == 6      # the policy's own fallback gap
    with pytest.raises(InputError, match="schedule.keyframe_every"):
        build_config(overrides=["schedule.keyframe_every=4"])


def _leaves(d: dict, pre: tuple = ()):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, pre + (k,))
        else:
            yield pre + (k,), v


def test_scene_presets_state_only_what_differs_from_their_base():
    """A preset with ``base:`` must not repeat a value of its base (it would hide a later change of the base)."""
    d = ROOT / "configs" / "dataset"
    children = 0
    for name in list_presets("dataset"):
        data = yaml.safe_load((d / f"{name}.yaml").read_text()) or {}
        if "base" not in data:
            continue
        children += 1
        base = dict(_leaves(build_config(data["base"], mode="fused").model_dump(mode="json")))
        repeated = [".".join(k) for k, v in _leaves({k: v for k, v in data.items() if k not in ("base", "modes")})
                    if base.get(k) == v]
        assert not repeated, f"{name}: repeats its base {data['base']}: {repeated}"
    assert children >= 14   # replica x7, scannet x5, tum x2


def test_every_preset_loads_in_every_mode():
    for name in list_presets("dataset"):
        for mode in ("field", "frontend", "fused"):
            build_config(name, mode=mode)


def test_a_preset_inherits_its_base_and_overrides_it(tmp_path):
    child = tmp_path / "mine.yaml"
    child.write_text("base: replica\nbound: [[0, 1], [0, 1], [0, 1]]\nfield: {mapping: {iters: 3}}\n")
    cfg, base = build_config(str(child), mode="fused"), build_config("replica", mode="fused")
    assert cfg.bound == [[0, 1], [0, 1], [0, 1]] and cfg.field.mapping.iters == 3
    assert cfg.field.tracking == base.field.tracking and cfg.dataset == base.dataset
    loop = tmp_path / "loop.yaml"
    loop.write_text(f"base: {loop}\n")
    with pytest.raises(InputError, match="cycle"):
        build_config(str(loop))
