"""docs/configs.md is what `python -m realityavatar.configs_doc` makes from conf/ (regenerate it when this fails)."""

from __future__ import annotations

import pytest

from realityavatar import configs_doc


def test_committed_configs_doc_is_current():
    assert configs_doc.OUT.is_file(), "docs/configs.md is missing: run `python -m realityavatar.configs_doc`"
    assert configs_doc.OUT.read_text() == configs_doc.render(), (
        "docs/configs.md is stale: run `python -m realityavatar.configs_doc` and commit it")


def test_check_flag_reports_a_stale_file(tmp_path):
    out = tmp_path / "configs.md"
    assert configs_doc.main(["--check", "--out", str(out)]) == 1  # missing
    assert configs_doc.main(["--out", str(out)]) == 0
    assert configs_doc.main(["--check", "--out", str(out)]) == 0
    out.write_text(out.read_text().replace("| `temporal` | **lstm** |", "| `temporal` | **gru** |"))
    assert configs_doc.main(["--check", "--out", str(out)]) == 1


def test_parse_reads_values_and_the_comments_beside_them(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text(
        "# @package _global_\n"
        "# What the file is for.\n"
        "defaults:\n"
        "  # the shared part\n"
        "  - base          # the shared settings\n"
        "  - _self_\n"
        "\n"
        "a: 1              # why a\n"
        "                  # and more on a\n"
        "# about b\n"
        "b: 'x # not a comment'\n"
        "c:                # a group\n"
        "  d: [1, 2]\n"
        "  e: ???\n")
    header, rows = configs_doc.parse(p)
    assert header == "What the file is for."
    got = {r["key"]: (r["value"], r["comment"]) for r in rows}
    assert got["defaults"] == ("[base, _self_]", "")
    assert rows[0]["items"] == [("base", "the shared settings", "the shared part"), ("_self_", "", "")]
    assert got["a"] == ("1", "why a and more on a")
    assert got["b"] == ("'x # not a comment'", "about b")
    assert got["c"] == ("", "a group")
    assert got["c.d"] == ("[1, 2]", "") and got["c.e"] == ("???", "")


def test_an_effect_for_an_option_that_is_gone_stops_the_generator(monkeypatch):
    monkeypatch.setitem(configs_doc.EFFECTS, "gaussians/hull", "-0.60 dB")
    with pytest.raises(ValueError, match="'gaussians/hull'"):
        configs_doc.render()
    monkeypatch.delitem(configs_doc.EFFECTS, "gaussians/hull")
    monkeypatch.setitem(configs_doc.EFFECTS, "sheet/skirt:no_such_key", "+1 dB")
    with pytest.raises(ValueError, match="no_such_key"):
        configs_doc.render()
