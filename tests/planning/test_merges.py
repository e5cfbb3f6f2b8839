"""Datasets that two config files define: what Snakemake's merge took from each, said."""

from __future__ import annotations

import re

import pytest
import yaml
from synthetic import make_dataset
from workflow_helpers import REPO, dry_run, snakemake_command, toy_config, write_config

from vprflow.core.errors import DatasetError
from vprflow.data.download import awaiting_download
from vprflow.planning.config import validate_config
from vprflow.planning.merges import dataset_merges, merge_order, without_foreign_downloads

SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
SHIPPED = REPO / "config" / "config.yaml"
# A dataset of one's own under the shipped name `corridor`, in a folder of its own.
MINE = {
    "datasets": {
        "corridor": {
            "path": "my_corridor",
            "reference": "db",
            "query": "queries",
            "ground_truth": {"kind": "none"},
            "methods": ["anyloc_vlad"],
        }
    }
}


def write(path, content: dict):
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return str(path)


def test_a_dataset_of_ones_own_reusing_a_shipped_name_is_named_with_the_keys_from_each_file(
    tmp_path,
):
    mine = write(tmp_path / "mine.yaml", MINE)
    (merge,) = dataset_merges([SHIPPED, mine])
    assert merge.name == "corridor"
    shipped = merge.files[0]
    assert merge.keys[mine] == ("ground_truth.kind", "methods", "path", "query", "reference")
    # The shipped entry's keys the user did not give stay, the truth file among them.
    assert set(merge.keys[shipped]) >= {"download", "rerank", "recall_at", "ground_truth.file"}
    note = merge.note()
    for said in ("'corridor'", shipped, mine, "rerank", "ground_truth.file", "a name of its own"):
        assert said in note


def test_a_download_is_left_out_where_another_file_named_the_datasets_folder(tmp_path):
    mine = write(tmp_path / "mine.yaml", MINE)
    (merge,) = dataset_merges([SHIPPED, mine])
    assert merge.foreign_download == merge.files[0] and merge.folder == "my_corridor"
    assert merge.left_out == ("download", "source")
    assert "nothing is downloaded into 'my_corridor'" in merge.note()
    merged = yaml.safe_load(SHIPPED.read_text())
    merged["datasets"]["corridor"].update(MINE["datasets"]["corridor"])
    merged["data_root"] = str(tmp_path / "data")
    assert "corridor" in awaiting_download(merged)  # what used to be fetched there
    kept = without_foreign_downloads(merged, [merge])
    assert awaiting_download(kept) == ["roadscene"]
    assert "download" in merged["datasets"]["corridor"]  # the caller's config as given


def test_a_later_file_naming_the_same_folder_keeps_the_download(tmp_path):
    own = {**MINE["datasets"]["corridor"], "path": "corridor"}
    mine = write(tmp_path / "mine.yaml", {"datasets": {"corridor": own}})
    (merge,) = dataset_merges([SHIPPED, mine])
    assert merge.foreign_download is None and "downloaded" not in merge.note()


def test_a_file_that_only_adjusts_another_files_dataset_goes_unremarked():
    assert dataset_merges([SHIPPED, REPO / "config" / "trained.yaml"]) == []
    # The same folders restated, with its own methods and resolution: the same images.
    assert dataset_merges([SHIPPED, REPO / ".test" / "config" / "config.yaml"]) == []


def test_the_workflows_own_config_file_merges_first_and_the_command_lines_in_their_order():
    workflow_files = ["/w/a.yaml", "/w/b.yaml", "config/config.yaml"]
    assert merge_order(workflow_files, ["/w/a.yaml", "/w/b.yaml"]) == [
        "config/config.yaml",
        "/w/a.yaml",
        "/w/b.yaml",
    ]
    # Named on the command line too: it merges there (and again: the same values).
    assert merge_order([str(SHIPPED), "/w/m.yaml", str(SHIPPED)], [str(SHIPPED), "/w/m.yaml"]) == [
        str(SHIPPED),
        "/w/m.yaml",
    ]


def test_validating_merged_files_says_what_was_merged_and_downloads_nothing(tmp_path, capsys):
    mine = write(tmp_path / "mine.yaml", MINE)
    raw = yaml.safe_load(SHIPPED.read_text())
    raw["datasets"]["corridor"].update(MINE["datasets"]["corridor"])
    raw["data_root"] = str(tmp_path / "data")
    config = validate_config(raw, SCHEMA, [SHIPPED, mine])
    assert "download" not in config["datasets"]["corridor"]
    assert "corridor" not in awaiting_download(config)
    err = capsys.readouterr().err
    assert "vprflow: dataset 'corridor' is defined in" in err and mine in err


@pytest.mark.workflow
def test_a_run_with_ones_own_dataset_under_a_shipped_name_says_so_and_downloads_nothing(tmp_path):
    """The shipped-like `toy` (with a download entry) and a file of one's own defining
    `toy` in its own folder: the dry run names both files and the folder, and schedules
    no download (it used to unpack the shipped archive into the user's folder)."""
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    config = toy_config(tmp_path / "data")
    config["datasets"]["toy"]["download"] = {"url": "file:///nowhere.tar.gz", "layout": {".": "."}}
    shipped = write_config(tmp_path, config)
    own = {**config["datasets"]["toy"], "path": "my_toy"}
    del own["download"]
    mine = write_config(tmp_path, {"datasets": {"toy": own}}, "mine.yaml")
    command = snakemake_command(tmp_path, shipped, "-n", "results/recall_toy.csv")
    at = command.index(str(shipped))
    command[at + 1 : at + 1] = [str(mine)]  # `--configfile shipped mine`
    result = dry_run(command, tmp_path)
    text = result.stdout + result.stderr
    assert result.returncode != 0
    assert not re.search(r"^download +1$", text, re.M)
    assert "dataset 'toy' is defined in" in text and "nothing is downloaded into 'my_toy'" in text
    assert f"folder {tmp_path / 'data' / 'my_toy'} does not exist" in text
    assert DatasetError.__name__ in text
