"""Site names with control characters are refused; one broken site.toml does not hide the others."""

from __future__ import annotations

import pytest
from test_sites import make_project

from fieldtool.cli.main import main
from fieldtool.errors import ParameterError
from fieldtool.records.sites import BrokenSite, check_name, list_sites


@pytest.mark.parametrize("name", ["nl\n", "tab\there", "bell\x07", "a\rb", "del\x7f", "\nlead"])
def test_names_with_control_characters_are_refused(tmp_path, capsys, name):
    with pytest.raises(ParameterError, match="control character"):
        check_name(name)
    src = make_project(tmp_path / "p")
    root = tmp_path / "sites"
    assert main(["site", "create", name, "--from", str(src), "--sites", str(root)]) == 2
    err = capsys.readouterr().err
    assert "control character" in err and len(err.strip().splitlines()) == 1
    assert not root.exists() or list(root.iterdir()) == []


def test_one_broken_site_toml_is_listed_as_broken_and_the_others_still_are(tmp_path, capsys):
    src = make_project(tmp_path / "p")
    root = tmp_path / "sites"
    for name in ("alpha", "beta", "gamma"):
        assert main(["site", "create", name, "--from", str(src), "--sites", str(root)]) == 0
    (root / "beta" / "site.toml").write_text("[site\nname = ")  # damaged
    (root / "gamma" / "site.toml").write_text('[site]\nname = "gamma"\n[project]\nnonsense_key = 1\n')
    capsys.readouterr()
    broken: list[BrokenSite] = []
    assert [s.name for s in list_sites(root, broken)] == ["alpha"]
    assert [b.name for b in broken] == ["beta", "gamma"]
    assert "not valid TOML" in broken[0].reason and "nonsense_key" in broken[1].reason
    assert main(["site", "list", "--sites", str(root)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("alpha")
    assert "'beta'" in out and "BROKEN" in out and "not valid TOML" in out and "nonsense_key" in out
