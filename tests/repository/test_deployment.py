"""How the workflow is deployed stays in step with the package: the rules' conda
environment (workflow/envs/vprflow.yaml) takes Python from requires-python's range and
every other dependency from pyproject.toml, every rule that runs something uses it,
every stage of the plan's table has its rule, and the catalog file and the profiles'
README describe what is there."""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

import yaml
from packaging.specifiers import SpecifierSet

from vprflow.planning.plan import STAGES

REPO = Path(__file__).resolve().parents[2]
WORKFLOW = REPO / "workflow"
ENV = WORKFLOW / "envs" / "vprflow.yaml"
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
# Directives that make a rule run code (a rule with none, like `all`, only collects).
ACTIONS = ("script", "shell", "run", "notebook", "wrapper", "cwl")
RULE = re.compile(r"^(?:rule|checkpoint)\s+(\w+)\s*:")


def rules() -> dict[str, tuple[Path, dict[str, str]]]:
    """Every rule in the Snakefile and workflow/rules/*.smk -> (its file, its directives
    as ``name: first value line``). snakefmt keeps rules in this layout."""
    found = {}
    for path in [WORKFLOW / "Snakefile", *sorted((WORKFLOW / "rules").glob("*.smk"))]:
        name, directives, directive = None, {}, None
        for line in [*path.read_text().splitlines(), "end:"]:
            if line and not line[0].isspace() and not line.startswith("#"):
                if name:
                    found[name] = (path, directives)
                match = RULE.match(line)
                name, directives = (match.group(1), {}) if match else (None, {})
                continue
            if name is None or not line.strip():
                continue
            key = re.match(r"^    (\w+):\s*(.*)$", line)
            if key:
                directive = key.group(1)
                directives[directive] = key.group(2).strip()
            elif directive and not directives[directive]:
                directives[directive] = line.strip()
    return found


def test_every_rule_that_runs_code_uses_the_one_environment():
    parsed = rules()
    # The parser found the rules: one per stage (named after it) at least.
    assert set(STAGES) <= set(parsed), sorted(set(STAGES) - set(parsed))
    running = {n: r for n, r in parsed.items() if set(r[1]) & set(ACTIONS)}
    # Every rule of rules/*.smk runs code, but a target that only gathers inputs (as `all`).
    targets = {n for n, (_, d) in parsed.items() if set(d) <= {"input", "default_target"}}
    assert {n for n, (p, _) in parsed.items() if p.parent.name == "rules"} - targets <= set(running)
    for name, (path, directives) in running.items():
        assert "conda" in directives, f"rule {name} ({path.name}) has no conda: environment"
        env = (path.parent / ast.literal_eval(directives["conda"])).resolve()
        assert env == ENV, f"rule {name} ({path.name}) uses {env}, not {ENV}"


def test_every_stage_of_the_plans_table_has_its_rule_and_every_stage_rule_a_stage():
    """The rules that run the stage script are the table's stages, each named after its
    stage, in a file the Snakefile includes, planned by its own name, writing shards
    exactly when the table shards the stage (and the gather rule takes those stages)."""
    parsed = rules()
    runs_a_stage = {n for n, (_, d) in parsed.items() if d.get("script") == '"../scripts/stage.py"'}
    assert runs_a_stage == set(STAGES)
    snakefile = (WORKFLOW / "Snakefile").read_text()
    for name, stage in STAGES.items():
        path, directives = parsed[name]
        assert f'include: "rules/{path.name}"' in snakefile, path
        assert directives["params"] == f'record=stage_record("{name}"),', name
        if "input" in directives:  # the images stage reads no store
            assert directives["input"] == f'unpack(stage_inputs("{name}")),', name
        output = (
            f'temp(directory(shard_pattern("{name}"))),'
            if stage.shards
            else f'directory(store_pattern("{name}")),'
        )
        assert directives["output"] == output, name
    gather = parsed["gather"][1]
    assert gather["wildcard_constraints"] == "stage=SHARDED_STAGES,"


def environment() -> tuple[list[str], list[str]]:
    """(conda dependencies, pip entries) of the rules' environment."""
    spec = yaml.safe_load(ENV.read_text())
    conda = [d for d in spec["dependencies"] if isinstance(d, str)]
    pip = [entry for d in spec["dependencies"] if isinstance(d, dict) for entry in d["pip"]]
    return conda, pip


def test_the_environment_python_is_one_the_package_supports():
    conda, _ = environment()
    pythons = [d for d in conda if re.match(r"python\b", d)]
    assert len(pythons) == 1, conda
    version = re.fullmatch(r"python\s*=+\s*([\d.]+)\*?", pythons[0])
    assert version, f"{pythons[0]!r}: pin a version, e.g. python=3.11"
    supported = SpecifierSet(PYPROJECT["project"]["requires-python"])
    assert version.group(1) in supported, (
        f"{ENV.name} installs python {version.group(1)}, outside requires-python {supported}"
    )


def test_the_environment_installs_this_package_and_nothing_else():
    """Dependencies live in pyproject.toml only: the environment installs the package
    from this checkout (which pulls them in), so the two cannot list different ones."""
    conda, pip = environment()
    extra = [d for d in conda if not re.match(r"(python|pip)\b", d)]
    assert not extra, f"{ENV.name} lists {extra}: add them to pyproject.toml instead"
    assert "pip" in conda, conda
    assert len(pip) == 1 and pip[0].startswith("-e "), pip
    target = (ENV.parent / pip[0].removeprefix("-e ").strip()).resolve()
    assert target == REPO, f"{ENV.name} installs {target}, not the repository {REPO}"
    assert PYPROJECT["project"]["name"] == "vprflow"


def test_the_catalog_file_describes_this_repository():
    catalog = yaml.safe_load((REPO / ".snakemake-workflow-catalog.yml").read_text())
    usage = catalog["usage"]
    # conda: true promises `--sdm conda` works: the environment tests above make it so.
    assert usage["software-stack-deployment"] == {"conda": True}
    assert usage["report"] is (
        re.search(r"^report:", (WORKFLOW / "Snakefile").read_text(), re.M) is not None
    )
    # The catalog shows config/README.md as the configuration's documentation.
    assert (REPO / "config" / "README.md").is_file()
    assert (REPO / "config" / "config.yaml").is_file()


def test_the_profiles_readme_describes_every_profile():
    readme = (WORKFLOW / "profiles" / "README.md").read_text()
    profiles = [p for p in (WORKFLOW / "profiles").iterdir() if p.is_dir()]
    assert profiles
    for profile in profiles:
        assert (profile / "config.yaml").is_file(), profile
        assert f"`{profile.name}`" in readme, f"workflow/profiles/README.md omits {profile.name}"


def readme_yaml_blocks() -> list[dict]:
    text = (REPO / "README.md").read_text()
    return [yaml.safe_load(block) for block in re.findall(r"```yaml\n(.*?)```", text, re.S)]


def test_the_readmes_own_image_recipes_validate_and_plan(tmp_path):
    """Both recipes of "Your own images" are files of one's own that Snakemake merges over
    the shipped config: they validate, and the plan is built for a folder of images laid
    out as said."""
    from snakemake.utils import update_config
    from synthetic import make_dataset
    from workflow_helpers import expected_rows, repo_config

    from vprflow.planning.config import validate_config
    from vprflow.planning.plan import build_plan

    recipes = readme_yaml_blocks()
    assert len(recipes) == 2
    make_dataset(tmp_path / "toy")
    (tmp_path / "mine").mkdir()
    (tmp_path / "toy" / "ref").rename(tmp_path / "mine" / "db")
    (tmp_path / "toy" / "query").rename(tmp_path / "mine" / "queries")
    for recipe in recipes:
        config = repo_config()
        config["data_root"] = str(tmp_path)
        recipe["datasets"]["mine"]["ground_truth"] = {"kind": "none"}  # gps.csv is the user's
        update_config(config, recipe)  # as `--configfile config/mine.yaml` merges it
        assert {"corridor", "mine"} <= set(config["datasets"]) and config["targets"] == ["mine"]
        plan = build_plan(validate_config(config, WORKFLOW / "schemas" / "config.schema.yaml"))
        assert [run.method for run in plan.runs["mine"]] == expected_rows(
            config["datasets"]["mine"]
        )


def test_the_readme_names_only_methods_the_shipped_config_defines():
    from workflow_helpers import repo_config

    text = (REPO / "README.md").read_text()
    config = repo_config()
    first_cells = re.findall(r"^\| (`[^|]*)\|", text, re.M)
    named = {name for cell in first_cells for name in re.findall(r"`([a-z0-9_]+)`", cell)}
    assert len(named) > 10 and named <= set(config["methods"]), named - set(config["methods"])
