"""The package's shape: wings whose imports flow one way, no import cycle, and the flat
module paths of 0.1 still importable (with a warning) for one release."""

import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from script_helpers import load_script

import vprflow

PACKAGE = Path(vprflow.__file__).parent

# The graph is read by scripts/import_graph.py (which prints it): imports anywhere in a
# module, those inside functions included, each an arrow.
GRAPH = load_script("import_graph")
RANKS = GRAPH.RANKS


def _imports() -> dict[str, set[str]]:
    return GRAPH.imports(PACKAGE)


# What the stages share: a job, every store's readers, the retrieval, a descriptor of one
# image. A runner (the function of one rule) imports these, never another runner.
STAGE_SUPPORT = {"base", "readers", "retrieval", "image_descriptors"}


def test_every_folder_of_the_package_is_a_ranked_wing():
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(RANKS)
    flat = {p.stem for p in PACKAGE.glob("*.py")}
    assert flat == {"__init__"}, "modules belong in a wing"


def test_the_import_graph_is_read():
    graph = _imports()
    assert "vprflow.core.stores" in graph["vprflow.stages.gather"]
    assert "vprflow.data.ground_truth" in graph["vprflow.stages.dataset"]
    assert sum(map(len, graph.values())) > 100


def test_imports_between_wings_flow_down_only():
    assert GRAPH.upward(_imports()) == []


def test_no_module_takes_part_in_an_import_cycle():
    assert GRAPH.cycles(_imports()) == []


def test_the_cycle_finder_finds_a_cycle_through_a_lazy_import():
    graph = {"vprflow.a.x": {"vprflow.a.y"}, "vprflow.a.y": {"vprflow.a.x"}, "vprflow.a.z": set()}
    assert GRAPH.cycles(graph) == [["vprflow.a.x", "vprflow.a.y"]]
    assert GRAPH.upward({"vprflow.core.x": {"vprflow.stages.y"}}) == [
        "vprflow.core.x -> vprflow.stages.y"
    ]


@pytest.mark.parametrize("old", sorted(vprflow.MOVED))
def test_an_old_module_path_imports_the_moved_module_with_a_warning(old):
    sys.modules.pop(f"vprflow.{old}", None)
    with pytest.warns(
        DeprecationWarning, match=f"vprflow.{old} moved to vprflow.{vprflow.MOVED[old]}"
    ):
        module = importlib.import_module(f"vprflow.{old}")
    assert module is importlib.import_module(f"vprflow.{vprflow.MOVED[old]}")


def test_every_moved_module_exists():
    for new in vprflow.MOVED.values():
        assert (PACKAGE / (new.replace(".", "/") + ".py")).exists() or (
            PACKAGE / new.replace(".", "/") / "__init__.py"
        ).exists(), new


def test_the_old_hub_names_of_vprflow_models_resolve_with_a_warning():
    from vprflow.models import hub

    with pytest.warns(DeprecationWarning, match="vprflow.models.hub.load_pretrained"):
        from vprflow.models import load_pretrained
    assert load_pretrained is hub.load_pretrained


def test_new_paths_import_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        importlib.import_module("vprflow.planning.plan")
        importlib.import_module("vprflow.stages.jobs")


def test_no_module_names_code_by_a_module_name_string():
    """Every tie between modules is an import the graph sees: no ``"module:function"``
    string anywhere in the package, and no lookup in ``globals()``."""
    assert GRAPH.string_ties(PACKAGE) == []
    assert not [x for x in GRAPH.dynamic_lookups(PACKAGE) if "globals()" in x]


def test_the_string_tie_finder_finds_one():
    assert GRAPH.TIE.match("vprflow.models.vit:load_vit")
    assert not GRAPH.TIE.match("vprflow.models.vit")


def test_planning_imports_no_torch():
    """Planning reads every wing's entries (model kinds, aggregators, search indexes,
    re-rankers) without importing a model: the loaders import theirs when they run."""
    code = (
        "import sys, vprflow.planning.plan, vprflow.planning.config, vprflow.stages.jobs; "
        "print(sorted(m for m in ('torch', 'faiss', 'cv2', 'transformers') if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"


def test_no_stage_runner_imports_another_runner():
    """Only stages/jobs.py, which binds every rule to its runner, imports runners; the
    runners meet in the readers and the retrieval."""
    graph = _imports()
    stages = {m for m in graph if m.startswith("vprflow.stages.")}
    runners = {m for m in stages if m.rsplit(".", 1)[1] not in STAGE_SUPPORT | {"jobs"}}
    crossing = sorted((m, t) for m in stages - {"vprflow.stages.jobs"} for t in graph[m] & runners)
    assert crossing == []
    assert {f"vprflow.stages.{name}" for name in STAGE_SUPPORT} <= stages
