"""The generated reference pages (docs/api.md, docs/cli.md) match the code: regenerate them
with ``PYTHONPATH=src python docs/gen_reference.py`` after changing a docstring or an option."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path
from types import ModuleType

import pytest

DOCS = Path(__file__).resolve().parent.parent / "docs"


def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_reference", DOCS / "gen_reference.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def generated() -> dict[str, str]:
    return _generator().generate()


def test_api_reference_is_up_to_date(generated: dict[str, str]) -> None:
    committed = (DOCS / "api.md").read_text(encoding="utf-8")
    assert committed == generated["api.md"], (
        "docs/api.md is out of date: run PYTHONPATH=src python docs/gen_reference.py")


def test_cli_reference_is_up_to_date(generated: dict[str, str]) -> None:
    committed = (DOCS / "cli.md").read_text(encoding="utf-8")
    wrote = re.search(r"argparse of Python (\d+\.\d+)", committed.splitlines()[0])
    here = f"{sys.version_info[0]}.{sys.version_info[1]}"
    if wrote is None or wrote.group(1) != here:
        pytest.skip(f"docs/cli.md was written by another Python's argparse ({wrote and wrote[1]})")
    assert committed == generated["cli.md"], (
        "docs/cli.md is out of date: run PYTHONPATH=src python docs/gen_reference.py")


def test_generator_writes_and_checks(tmp_path: Path, generated: dict[str, str]) -> None:
    gen = _generator()
    assert gen.main(["--out-dir", str(tmp_path)]) == 0
    for name, text in generated.items():
        assert (tmp_path / name).read_text(encoding="utf-8") == text
    assert gen.main(["--out-dir", str(tmp_path), "--check"]) == 0
    (tmp_path / "cli.md").write_text("stale\n", encoding="utf-8")
    assert gen.main(["--out-dir", str(tmp_path), "--check"]) == 1


def test_every_public_name_is_in_the_api_reference(generated: dict[str, str]) -> None:
    import hybridpgo

    for name in hybridpgo.__all__:
        assert f"### `hybridpgo.{name}`" in generated["api.md"]
    assert "### `hybridpgo.energy.residuals`" in generated["api.md"]
    assert "## hybridpgo optimize" in generated["cli.md"]
    assert "--covariance NPZ" in generated["cli.md"]


def test_doc_pages_link_to_existing_files() -> None:
    """Relative links of the hand-written pages point at files that exist."""
    for page in DOCS.glob("*.md"):
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", page.read_text(encoding="utf-8")):
            assert (page.parent / target).exists(), f"{page.name}: broken link {target}"


def _anchors(page: Path) -> set[str]:
    """The anchors of a page: explicit ``<a id="...">`` and GitHub's heading slugs."""
    text = page.read_text(encoding="utf-8")
    found = set(re.findall(r'<a id="([^"]+)"></a>', text))
    for heading in re.findall(r"^#+ (.+)$", text, re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        found.add(slug)
    return found


def _section_links() -> list[tuple[str, Path, str]]:
    """``(where, page, anchor)`` of every ``page.md#anchor`` link in the pages and every
    ``docs/page.md#anchor`` reference in the package's sources."""
    root = DOCS.parent
    out: list[tuple[str, Path, str]] = []
    for page in [root / "README.md", *DOCS.glob("*.md")]:
        text = page.read_text(encoding="utf-8")
        for target, anchor in re.findall(r"\]\(([^)#:]*)#([^)]+)\)", text):
            out.append((page.name, (page.parent / target) if target else page, anchor))
    for src in sorted((root / "src").rglob("*.py")):
        for target, anchor in re.findall(r"docs/(\w[\w-]*\.md)#([\w-]+)", src.read_text(
                encoding="utf-8")):
            out.append((str(src.relative_to(root)), DOCS / target, anchor))
    return out


def test_section_links_name_existing_anchors() -> None:
    """Every ``page.md#anchor`` of the pages and of the code names an anchor that exists."""
    links = _section_links()
    assert links  # the pages do link to sections
    for where, page, anchor in links:
        assert page.exists(), f"{where}: {page.name} does not exist"
        assert anchor in _anchors(page), f"{where}: {page.name} has no anchor #{anchor}"
