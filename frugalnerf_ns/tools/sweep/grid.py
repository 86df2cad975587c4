"""What a sweep runs: run specs from a grid file (scene x views x method x options x seed).

A grid file (``configs/sweeps/*.yaml``)::

    scenes_file: ../benchmark_scenes.yaml   # scene definitions, relative to this file
    scenes: [fern, flower]                  # names in the scenes file
    views: [2, 3]                           # view counts each scene defines
    methods: [scene-preset, tensorf]        # FrugalNeRF presets, `scene-preset`, or baselines of the scenes file
    options:                                # named override sets (dotted config path -> value), FrugalNeRF only
      full: {}
      no-geo: {pipeline.model.geo_weight: 0}
    seeds: [42, 43]                         # null: the method's own default
    max_iterations: null                    # every method's budget (null: its own)
    anytime_every: null                     # also score a checkpoint every N steps

A scene in the scenes file gives ``data`` (relative to the file's ``data_root``, itself relative to the file;
without one, the repository root, or the current folder for an installed package), the
dataparser and its options (``parser``), the options that pick each view count (``views``), extra dataparser
options for nerfstudio's methods (``baseline_options``) and its CPU preset (``preset``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

import yaml

from frugalnerf_ns.config_files import checkout_root

SCENE_PRESET = "scene-preset"


class GridError(ValueError):
    """A grid or scenes file that cannot be expanded; the message names the file and the entry."""


@dataclass(frozen=True)
class RunSpec:
    """One training run and its evaluation, as the sweep schedules it."""

    scene: str
    views: int
    method: str  # registered nerfstudio method (FrugalNeRF preset or baseline)
    option: str  # name of the override set ("full": none)
    data: str
    parser_args: List[str]
    train_args: List[str]  # ns-train options (overrides, budget, seed)
    seed: Optional[int] = None
    anytime_every: Optional[int] = None
    extra: Dict[str, Any] = field(default_factory=dict)  # front-end labels (not part of the key)

    @property
    def label(self) -> str:
        return self.method if self.option == "full" else f"{self.method}[{self.option}]"

    @property
    def key(self) -> str:
        """Hash of everything that changes the run's result: finished runs are found by it."""
        # The scene by name, not by path: the same sweep resumed where the data lives elsewhere finds its runs.
        what = [self.method, self.scene, self.parser_args, self.train_args, self.seed, self.anytime_every]
        return hashlib.sha1(json.dumps(what, sort_keys=True).encode()).hexdigest()[:12]

    def to_dict(self) -> Dict[str, Any]:
        return {**asdict(self), "label": self.label, "key": self.key}


def cli_option(path: str, value: Any) -> List[str]:
    """``pipeline.model.geo_weight: 0`` -> ``--pipeline.model.geo-weight 0`` (tyro's spelling)."""
    flag = "--" + path.replace("_", "-")
    if isinstance(value, bool):
        return [flag, str(value)]
    if isinstance(value, (list, tuple)):
        return [flag, *map(str, value)]
    return [flag, str(value)]


def override_args(overrides: Mapping[str, Any]) -> List[str]:
    return [arg for path, value in overrides.items() for arg in cli_option(path, value)]


def seed_args(method: str, seed: Optional[int]) -> List[str]:
    """Options that seed one run: torch/numpy/random for every method, our batch sampler for ours."""
    if seed is None:
        return []
    ours = ["--pipeline.datamanager.seed", str(seed)] if is_frugalnerf(method) else []
    return ["--machine.seed", str(seed), *ours]


def is_frugalnerf(method: str) -> bool:
    return method.startswith("frugalnerf")


def load_scenes(path: Path) -> Dict[str, Any]:
    try:
        table = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise GridError(f"{path}: cannot read the scenes file ({err})") from None
    if not isinstance(table, dict) or "scenes" not in table:
        raise GridError(f"{path}: no `scenes:` section")
    return table


def data_root_of(scenes_file: Path, table: Mapping[str, Any], data_root: Optional[Path] = None) -> Path:
    """Where the scenes' ``data`` paths start: ``data_root`` if given, else the file's own ``data_root``
    (relative to the file), else the repository root (the current folder for an installed package)."""
    if data_root is not None:
        return Path(data_root).resolve()
    root = Path(table.get("data_root") or checkout_root() or Path.cwd())
    return root if root.is_absolute() else (Path(scenes_file).parent / root).resolve()


def scene_data(scenes_file: Path, table: Mapping[str, Any], name: str, data_root: Optional[Path] = None) -> Path:
    return (data_root_of(scenes_file, table, data_root) / table["scenes"][name]["data"]).resolve()


def scene_parser(scenes_file: Path, table: Mapping[str, Any], name: str, views: int, baseline: bool) -> tuple:
    """(data path, dataparser args) of scene ``name`` with ``views`` training views."""
    if name not in table["scenes"]:
        raise GridError(f"{scenes_file}: unknown scene {name!r} (it has {', '.join(table['scenes'])})")
    scene = table["scenes"][name]
    choices = {int(k): v for k, v in (scene.get("views") or {}).items()}
    if views not in choices:
        raise GridError(f"{scenes_file}: scene {name!r} defines no {views}-view split (it has {sorted(choices)})")
    args = [*map(str, scene["parser"]), *map(str, choices[views])]
    if baseline:
        args += [*map(str, scene.get("baseline_options") or [])]
    return str(scene["data"]), args


def expand(
    scenes_file: Path,
    scenes: Sequence[str],
    views: Sequence[int],
    methods: Sequence[str],
    options: Mapping[str, Sequence[str]],
    seeds: Sequence[Optional[int]],
    max_iterations: Optional[int] = None,
    anytime_every: Optional[int] = None,
    data_root: Optional[Path] = None,
) -> List[RunSpec]:
    """Every (scene, views, method, option, seed). ``options`` maps a name to ns-train args; nerfstudio's own
    methods run once per scene, views and seed, with the scenes file's baseline args instead."""
    table = load_scenes(scenes_file)
    baselines = table.get("baselines") or {}
    budget = ["--max-num-iterations", str(max_iterations)] if max_iterations else []
    unknown = [name for name in scenes if name not in table["scenes"]]
    if unknown:
        raise GridError(f"{scenes_file}: unknown scene {unknown[0]!r} (it has {', '.join(table['scenes'])})")
    specs: List[RunSpec] = []
    for scene in scenes:
        for count in views:
            for requested in methods:
                method = table["scenes"][scene].get("preset", requested) if requested == SCENE_PRESET else requested
                ours = is_frugalnerf(method)
                if not ours and method not in baselines:
                    raise GridError(f"{scenes_file}: method {method!r} is neither a FrugalNeRF preset nor one of its "
                                    f"baselines ({', '.join(baselines) or 'none'})")
                _, parser_args = scene_parser(scenes_file, table, scene, count, baseline=not ours)
                sets = options.items() if ours else [("full", [*map(str, baselines[method].get("args", []))])]
                for option, args in sets:
                    for seed in seeds:
                        train_args = [*args, *budget, *seed_args(method, seed)]
                        if anytime_every:
                            train_args += ["--steps-per-save", str(anytime_every), "--save-only-latest-checkpoint", "False"]
                        specs.append(RunSpec(scene, int(count), method, option,
                                             str(scene_data(scenes_file, table, scene, data_root)), parser_args,
                                             train_args, seed, anytime_every))
    keys = [s.key for s in specs]
    if len(set(keys)) != len(keys):
        raise GridError("the grid lists the same run twice (two option sets with the same overrides?)")
    return specs


def load_grid(path: Path, data_root: Optional[Path] = None, max_iterations: Optional[int] = None) -> List[RunSpec]:
    """Run specs of a grid file (format in this module's docstring)."""
    path = Path(path)
    try:
        grid = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise GridError(f"{path}: cannot read the grid file ({err})") from None
    if not isinstance(grid, dict):
        raise GridError(f"{path}: a grid file is a mapping (scenes, views, methods, options, seeds)")
    unknown = set(grid) - {"scenes_file", "scenes", "views", "methods", "options", "seeds", "max_iterations", "anytime_every"}
    if unknown:
        raise GridError(f"{path}: unknown keys {sorted(unknown)}")
    scenes_file = (path.parent / grid.get("scenes_file", "../benchmark_scenes.yaml")).resolve()
    raw_options = grid.get("options") or {"full": {}}
    options = {}
    for name, overrides in raw_options.items():
        if not isinstance(overrides, dict):
            raise GridError(f"{path}: option set {name!r} must map dotted config paths to values")
        options[str(name)] = override_args(overrides)
    for key in ("scenes", "methods"):
        if not grid.get(key):
            raise GridError(f"{path}: `{key}:` is empty or missing")
    return expand(
        scenes_file, grid["scenes"], grid.get("views") or [2], grid["methods"], options, grid.get("seeds") or [None],
        max_iterations if max_iterations is not None else grid.get("max_iterations"), grid.get("anytime_every"), data_root,
    )
