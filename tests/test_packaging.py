"""Packaging: the wheel carries the bundled models and runs outside the checkout; where ds3d looks
for its models (ds3d.util.paths); the client SDK needs no torch."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest

import ds3d.image2d.estimator
import ds3d.lifter
import ds3d.pipeline
import ds3d.util.paths
from ds3d.errors import DataFormatError
from ds3d.util.paths import MODEL_DIR_ENV, PACKAGE_MODELS_DIR, PROJECT_ROOT
from tests.needs import missing

PIP = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]  # the project venv's
PYPROJECT = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())
# What the wheel carries of models/, under ds3d/models/: what the models need at run time.
MODEL_FILES = {
    "MODEL_CARD.md",
    "image2d/manifest.json",
    "image2d/joint_calibration.json",
    "image2d/person_score.json",
    "image2d/psm.pt",
    "image2d/facing.pt",
    "image2d/jointnet.pt",
    "image2d/jointnet_int8.onnx",  # the joint network on CPUs without bfloat16
    "image2d/forest1.pt.gz",
    "image2d/forest2.pt.gz",
    "posedb/manifest.json",
    "posedb/poses.npy",
    "posedb-cmu/manifest.json",
    "posedb-cmu/poses.npy",
}


def test_every_package_of_the_source_tree_is_listed_in_pyproject():
    """pyproject.toml lists the packages (ds3d.models is mapped onto models/): a new one left
    out of the list would be left out of the wheel."""
    setuptools = PYPROJECT["tool"]["setuptools"]
    assert setuptools["package-dir"] == {"ds3d.models": "models"}
    found = {
        ".".join(folder.relative_to(PROJECT_ROOT).parts)
        for top in ("ds3d", "ds3d_service")
        for folder in [PROJECT_ROOT / top, *(PROJECT_ROOT / top).rglob("*")]
        if folder.is_dir() and any(folder.glob("*.py"))
    }
    assert found | {"ds3d.models"} == set(setuptools["packages"])


def test_models_dir_is_the_env_var_else_the_checkout(monkeypatch, tmp_path):
    monkeypatch.setenv(MODEL_DIR_ENV, str(tmp_path))
    assert ds3d.util.paths.models_dir() == tmp_path
    monkeypatch.delenv(MODEL_DIR_ENV)
    assert ds3d.util.paths.in_checkout()  # the tests run from one
    assert ds3d.util.paths.models_dir() == PROJECT_ROOT / "models"


def test_missing_models_name_the_env_var_and_the_package_data(monkeypatch, tmp_path):
    nowhere = tmp_path / "nowhere"
    for module in (ds3d.util.paths, ds3d.lifter, ds3d.image2d.estimator, ds3d.pipeline):
        monkeypatch.setattr(module, "MODELS_DIR", nowhere)
    monkeypatch.delenv(MODEL_DIR_ENV, raising=False)
    loaders = (
        ds3d.lifter.Lifter.load,
        ds3d.image2d.estimator.PoseEstimator2D.load,
        ds3d.pipeline.Pipeline.load,
    )
    for load in loaders:
        with pytest.raises(DataFormatError) as info:
            load()
        message = str(info.value)
        assert str(nowhere) in message
        assert f"${MODEL_DIR_ENV} (unset)" in message
        assert str(PACKAGE_MODELS_DIR) in message
    monkeypatch.setenv(MODEL_DIR_ENV, str(nowhere))
    with pytest.raises(DataFormatError, match=re.escape(f"${MODEL_DIR_ENV} (= {nowhere})")):
        ds3d.lifter.Lifter.load()
    # A folder the caller names is reported as it is.
    with pytest.raises(DataFormatError, match="no such model folder or file"):
        ds3d.lifter.Lifter.load(tmp_path / "mine")


def test_client_sdk_imports_without_torch():
    """ds3d_service.client depends on httpx and numpy only: torch, faiss and fastapi blocked."""
    code = (
        "import sys\n"
        "for name in ('torch', 'faiss', 'fastapi'):\n"
        "    sys.modules[name] = None  # importing it raises ImportError\n"
        "import ds3d_service.client\n"
        "assert ds3d_service.client.PoseClient and ds3d_service.client.AsyncPoseClient\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=PROJECT_ROOT, check=True, timeout=60)


def _repository_copy(dest: Path) -> Path:
    """The repository's files as git sees them (tracked, and untracked but not ignored), copied
    to `dest`: the wheel is built there, so that no build/ is left in the checkout."""
    if shutil.which("git") is None:
        missing("no git: the wheel is built from the files of a git checkout")
    listing = ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"]
    listed = subprocess.run(listing, cwd=PROJECT_ROOT, capture_output=True, check=True).stdout
    for name in filter(None, listed.decode().split("\0")):
        source = PROJECT_ROOT / name
        if source.is_file():  # not one deleted in the working tree
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)
    return dest


def _fresh_venv(path: Path) -> Path:
    """A venv without pip whose packages are its own, then (a .pth file, read after its own
    site-packages) the project venv's: the dependencies without downloading them. A .pth line
    that names a folder only appends it to sys.path, so the project venv's own .pth files (the
    editable install's finder) are not run."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True)
    python = path / "bin" / "python"
    site = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    ours = dict.fromkeys([sysconfig.get_path("purelib"), sysconfig.get_path("platlib")])
    (Path(site) / "zz_ds3d_project_venv.pth").write_text("\n".join(ours) + "\n")
    return python


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_wheel_installs_and_predicts_outside_the_checkout(data_dir, tmp_path):
    from ds3d.data.lsp import load_lsp

    image = load_lsp(split="test").image_paths[0]
    dist = tmp_path / "dist"
    # as a user builds it: pip fetches the build backend pyproject.toml names (setuptools >= 77;
    # a venv of Python 3.11 holds an older one)
    subprocess.run(
        [*PIP, "wheel", "--no-deps", "-w", str(dist), "."],
        cwd=_repository_copy(tmp_path / "src"),
        check=True,
        timeout=120,
    )
    (wheel,) = dist.glob("ds3d-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
    assert {n.removeprefix("ds3d/models/") for n in names if n.startswith("ds3d/models/")} == (
        MODEL_FILES
    )
    tops = {name.split("/")[0] for name in names}
    assert {top for top in tops if not top.endswith(".dist-info")} == {"ds3d", "ds3d_service"}
    page = {p.name for p in (PROJECT_ROOT / "ds3d_service" / "static").iterdir()}  # the web page
    assert {n.removeprefix("ds3d_service/static/") for n in names if "/static/" in n} == page

    venv = tmp_path / "venv"
    python = _fresh_venv(venv)
    subprocess.run(
        [*PIP, "--python", str(python), "install", "--no-deps", "--no-index", str(wheel)],
        check=True,
        timeout=120,
    )
    env = {k: v for k, v in os.environ.items() if k not in (MODEL_DIR_ENV, "PYTHONPATH")}
    work = tmp_path / "work"  # outside the checkout
    work.mkdir()

    probe = (
        "import json, ds3d, ds3d.util.paths as p; print(json.dumps([ds3d.__file__, "
        "str(p.MODELS_DIR), p.in_checkout()]))"
    )
    found = subprocess.run(
        [python, "-c", probe], cwd=work, env=env, capture_output=True, text=True, check=True
    )
    module, models, in_checkout = json.loads(found.stdout)
    # The wheel's ds3d, not the checkout's, and the models of its package data.
    assert Path(module).resolve().is_relative_to(venv.resolve()), module
    assert not in_checkout
    assert Path(models).resolve() == Path(module).resolve().parent / "models"
    assert (Path(models) / "image2d" / "manifest.json").is_file()

    out = work / "result"
    subprocess.run(
        [venv / "bin" / "ds3d", "--quiet", "predict", str(image), "--out", str(out)],
        cwd=work,
        env=env,
        check=True,
        timeout=180,
    )
    (line,) = (out / "predictions.jsonl").read_text().splitlines()
    prediction = json.loads(line)
    assert prediction["people"]
    person = prediction["people"][0]
    assert [len(person["joints_2d"]), len(person["joints_2d"][0])] == [14, 2]
    assert [len(person["joints_3d"]), len(person["joints_3d"][0])] == [14, 3]
