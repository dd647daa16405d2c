"""The user guide builds: `mkdocs build --strict` on mkdocs.yml, into a temporary folder, with no warning.

Strict mode turns every warning (a page missing from the nav, a broken link or anchor, a missing image)
into a failure; the output is read as well so that a warning printed by a plugin outside mkdocs' own
logger fails the test too. The built pages must not load anything from another host (the guide is read
offline, in the field)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytest.importorskip("mkdocs", reason="mkdocs is not installed (pip install -e '.[dev]')")
pytest.importorskip("material", reason="mkdocs-material is not installed (pip install -e '.[dev]')")


@pytest.fixture(scope="module")
def built_site(tmp_path_factory):
    site = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d", str(site)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return proc, site


def test_guide_builds_strict_without_warnings(built_site):
    proc, site = built_site
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    problems = [line for line in log.splitlines() if re.search(r"\b(WARNING|ERROR)\b", line)]
    assert not problems, "\n".join(problems)
    assert (site / "index.html").is_file()


def test_every_page_of_the_nav_is_built(built_site):
    _, site = built_site
    for page in sorted((ROOT / "docs").glob("*.md")):
        built = site / f"{page.stem}.html"
        assert built.is_file(), f"{page.name} was not built"


def test_built_pages_load_nothing_from_another_host(built_site):
    """No Google Fonts, no CDN: every stylesheet, script and image of the pages is the site's own."""
    _, site = built_site
    remote = re.compile(r"""<(?:link|script|img)\b[^>]*\b(?:href|src)=["'](?:https?:)?//""", re.I)
    for html in site.rglob("*.html"):
        hits = remote.findall(html.read_text(encoding="utf-8"))
        assert not hits, f"{html.relative_to(site)} loads {hits[:3]}"


def test_keys_page_is_in_the_guide(built_site):
    """The generated key table reaches the built page (one row per key of docs/keys.md)."""
    _, site = built_site
    rows = [
        line for line in (ROOT / "docs" / "keys.md").read_text(encoding="utf-8").splitlines() if line.startswith("| `")
    ]
    html = (site / "keys.html").read_text(encoding="utf-8")
    assert len(rows) > 100
    assert html.count("<tr>") >= len(rows)
