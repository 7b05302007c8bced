"""The README and docs/ as a user reads them: every relative link resolves, every page is in the index, and the
README's export commands and TorchScript snippet run and give the checkpoint's own answer."""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")  # [text](target); images excluded
FENCE = re.compile(r"^```")


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _prose(text: str) -> str:
    """The text outside fenced code blocks (a link-like string in code is code, not a link)."""
    out, inside = [], False
    for line in text.split("\n"):
        if FENCE.match(line.strip()):
            inside = not inside
            continue
        if not inside:
            out.append(line)
    return "\n".join(out)


def broken_links(pages: list[Path]) -> list[str]:
    """'page: target' for each relative markdown link, and each docs/...md path named in the prose, that does not
    resolve to an existing file (fragments ignored; http(s), mailto and in-page anchors skipped)."""
    broken = []
    for page in pages:
        text = _prose(page.read_text())
        for target in LINK.findall(text):
            if re.match(r"^[a-z]+:", target) or target.startswith("#"):
                continue
            if not (page.parent / target.split("#")[0]).exists():
                broken.append(f"{page.name}: {target}")
        for named in re.findall(r"(?<![\w/.])docs/[\w/.-]+\.md", text):
            if not (ROOT / named).exists():
                broken.append(f"{page.name}: {named}")
    return broken


def test_every_relative_link_and_docs_path_resolves():
    assert broken_links(_pages()) == []


def test_the_link_check_finds_a_broken_link(tmp_path):
    # the check itself can fail: a page linking a missing file and naming a missing docs page
    fake = tmp_path / "page.md"
    fake.write_text("[ok](page.md) [gone](missing.md#x) and docs/design/gone.md\n```\n[in code](nowhere.md)\n```\n")
    assert broken_links([fake]) == ["page.md: missing.md#x", "page.md: docs/design/gone.md"]


def test_index_links_every_docs_page_once():
    index = ROOT / "docs" / "index.md"
    linked = [(index.parent / t.split("#")[0]).resolve() for t in LINK.findall(_prose(index.read_text()))]
    pages = {p.resolve() for p in (ROOT / "docs").rglob("*.md") if p != index}
    assert sorted(map(str, pages - set(linked))) == []
    md = [p for p in linked if p.suffix == ".md"]
    assert len(md) == len(set(md)), "a page is listed twice"


def test_no_reference_to_the_former_notes_folder():
    old = "docs/" + "notes/"  # spelled in two parts so that this file does not name it
    hits = []
    for folder in ("src", "tests", "bench", "configs", "docs"):
        for path in (ROOT / folder).rglob("*"):
            if path.is_file() and path.suffix in {".py", ".md", ".yaml", ".txt"} and old in path.read_text():
                hits.append(str(path.relative_to(ROOT)))
    hits += ["README.md"] if old in (ROOT / "README.md").read_text() else []
    assert hits == []
    assert not list((ROOT / "docs" / "notes").glob("*"))


def _section(title: str) -> str:
    text = (ROOT / "README.md").read_text()
    start = text.index(f"\n## {title}")
    end = text.find("\n## ", start + 1)
    return text[start : end if end > 0 else None]


def _blocks(section: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", section, flags=re.S)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The README's qcm-export command run on a tiny trained CNN and a tiny dataset laid out as the README says
    (data/small.h5, the checkpoint in place of the demo's): returns (folder, checkpoint)."""
    pytest.importorskip("onnxruntime")
    from hybridqcm.testing import synthetic_samples, train_tiny_checkpoints, write_dataset

    root = tmp_path_factory.mktemp("readme")
    checkpoint = train_tiny_checkpoints(root / "ckpt", synthetic_samples(32, n_steps=160, seed=0), steps=3, window=128)
    write_dataset(root / "data" / "small.h5", synthetic_samples(12, n_steps=160, seed=5))
    (line,) = [ln for ln in _blocks(_section("Export"), "bash")[0].split("\n") if ln.startswith("qcm-export ")]
    args = shlex.split(line.split("#")[0])[1:]
    assert args[0].endswith(".ckpt")
    args[0] = str(checkpoint["cnn"])
    # qcm-export's main() in-process, run from the folder the README's paths are relative to (a console start
    # costs more than the export; qcm-export's console: test_export_files)
    from hybridqcm.apps.export import main

    here = os.getcwd()
    os.chdir(root)
    try:
        main(args)
    finally:
        os.chdir(here)
    return root, checkpoint["cnn"]


def test_readme_torchscript_snippet_gives_the_checkpoints_estimates(exported, monkeypatch):
    import h5py

    from hybridqcm.models.checkpoint import load_checkpoint
    from hybridqcm.physics.parameters import PhysicalConstants

    root, checkpoint = exported
    (snippet,) = _blocks(_section("Export"), "python")
    monkeypatch.chdir(root)
    scope: dict = {}
    exec(compile(snippet, "README.md (Export)", "exec"), scope)

    # the same 8 recordings read here, not through the snippet, and the checkpoint's own (eager) estimate
    with h5py.File(root / "data" / "small.h5", "r") as f:
        accel = torch.from_numpy(f["test/accel"][:8, :128, :2])
    eager = load_checkpoint(checkpoint, "cnn").estimate(accel[..., 0], accel[..., 1])
    params = scope["params"]
    assert params.shape == (8, 2) and params.dtype == torch.float64
    assert torch.equal(scope["accel"], accel.transpose(1, 2))
    assert (params - eager).abs().max() <= 1e-6 * eager.abs().max(), (params, eager)
    assert (params > 0).all()
    assert torch.allclose(scope["m3"], PhysicalConstants().K3 / eager[:, 1], rtol=1e-6)

    # the ONNX one-liner after the block, on the snippet's input
    (onnx_line,) = re.findall(r"`(onnxruntime\.InferenceSession\(.*?)`", _section("Export"))
    import onnxruntime  # noqa: F401 - the one-liner's name

    onnx = torch.from_numpy(eval(onnx_line, {"onnxruntime": onnxruntime, **scope}))
    assert (onnx - eager).abs().max() <= 1e-5 * eager.abs().max()
