"""The GPU check: on a machine with an NVIDIA GPU and PyTorch, every figure of ds3d on CUDA
beside the same machine's CPU, in one run of a few minutes, written to one JSON report.

    python -m tools.gpu_check pack .gpu            # here: the data subset (and wheels, below)
    python -m tools.gpu_check run OUT [--data .gpu/data] [--wheels .gpu/wheels]

`pack` copies what the check reads of $DS3D_DATA into DIR/data: LSP's annotations and its first
--images test images, Human3.6M's cameras and every 64th frame of S11 (the protocol's frames).
With --wheels it also downloads, for Python 3.12 on x86-64 Linux, the wheels of the packages
that PyTorch images lack (faiss-cpu, FastAPI, uvicorn, pydantic and their needs) into
DIR/wheels. Together with the repository about 60 MB: small enough to copy to a bare machine.

`run` installs those wheels (when given) into a private folder, then runs each step below as
its own process under its own time limit, going on past a step that fails, and writes
OUT/gpu_check.json: per step its command, exit status, seconds and report (the JSON the step
wrote), and the tail of its log (OUT/STEP.log). The steps:
  env           nvidia-smi, torch and its CUDA
  tests         the CUDA tests (pytest -k cuda; they skip without CUDA)
  lift_cuda     ds3d bench lift on CUDA, batch 1, 64, 1,024 and 8,192; `_faiss`: retrieval by
                faiss on the CPU rather than on the device (LifterConfig.retrieval_on_device)
  pipeline_cuda ds3d bench pipeline on CUDA, people searched, batch 1 and 64; `_boxes`: each
                image's own box
  pipeline_cpu  the same on the CPU alone (CUDA_VISIBLE_DEVICES empty): 2 threads, all
                threads, and half as many worker processes of 2 threads as there are cores
                (`_2`, `_all`, `_workers`, ds3d.runners.workers): how the CPU path scales with cores
  eval_lsp      ds3d eval lsp on the packed test images, CUDA and CPU
  eval_h36m     ds3d eval h36m on the packed S11 frames, CUDA and CPU
  serve         ds3d-serve on CUDA, /v1/pose at concurrency 64 and /v1/lift (tools.loadtest)
  profile       torch.profiler of Pipeline.estimate on CUDA at batch 64, by op (tools.gpu_profile)
Imports only the standard library: it runs before anything is installed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LSP_TEST_FIRST = 1001  # im1001.jpg, LSP's first test image
H36M_STRIDE = 64  # the protocol's frames (ds3d eval h36m --stride)
# Wheels the 'cuda' images of PyTorch lack, pinned as requirements/service.txt pins them.
# onnxruntime (28 MB) is not among them, so that the pack stays within what the device carries:
# the machine's CPU runs the joint network in float32 there (quantized.int8_available).
WHEELS = (
    "faiss-cpu",
    "fastapi",
    "starlette",
    "pydantic",
    "pydantic-core",
    "pydantic-settings",
    "python-dotenv",
    "annotated-types",
    "typing-inspection",
    "uvicorn",
    "python-multipart",
    "prometheus-client",
)
PORT = 8791
LSP_POSES = """import json, sys
from ds3d.data.lsp import load_lsp
a = load_lsp()
poses = {"joints_2d": a.joints.tolist(), "visible": a.visible.tolist()}
json.dump(poses, open(sys.argv[1], "w"))"""
TORCH_INFO = (
    "import torch; "
    "print(torch.__version__, torch.version.cuda, torch.cuda.is_available(), "
    "torch.cuda.get_device_name() if torch.cuda.is_available() else None)"
)


def pack(out: Path, images: int, wheels: bool) -> None:
    """The data subset (and wheels) of the module docstring, into `out`."""
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from ds3d.util.paths import data_root

    source, data = data_root(), out / "data"
    (data / "lsp" / "images").mkdir(parents=True, exist_ok=True)
    (data / "h36m").mkdir(parents=True, exist_ok=True)
    shutil.copy(source / "lsp" / "joints.mat", data / "lsp")
    for i in range(LSP_TEST_FIRST, LSP_TEST_FIRST + images):
        shutil.copy(source / "lsp" / "images" / f"im{i:04d}.jpg", data / "lsp" / "images")
    shutil.copy(source / "h36m" / "cameras.h5", data / "h36m")
    with np.load(source / "h36m" / "poses_3d_17j.npz") as archive:
        s11 = {k: archive[k][::H36M_STRIDE] for k in archive.files if k.startswith("S11/")}
    np.savez_compressed(data / "h36m" / "poses_3d_17j.npz", **s11)
    if wheels:
        pins = _pins()
        command = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:"]
        command += ["--python-version", "3.12", "--implementation", "cp", "-d", str(out / "wheels")]
        for platform in ("manylinux_2_28", "manylinux_2_27", "manylinux_2_17", "manylinux2014"):
            command += ["--platform", f"{platform}_x86_64"]
        subprocess.run(command + [pins.get(name, name) for name in WHEELS], check=True)


def _pins() -> dict[str, str]:
    """{package: 'package==version'} of the lock requirements/service.txt."""
    pins = {}
    for line in (ROOT / "requirements" / "service.txt").read_text().splitlines():
        spec = line.split(" ")[0]
        if "==" in spec and not spec.startswith("#"):
            pins[spec.split("==")[0].lower()] = spec
    return pins


def run(out: Path, data: Path | None, wheels: Path | None) -> dict:
    """Every step of the module docstring; returns (and writes) the report."""
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if data is not None:
        env["DS3D_DATA"] = str(data.resolve())
    if wheels is not None:
        site = Path("/tmp/ds3d-gpu-site")
        pip = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps"]
        pip += ["--no-compile", "--upgrade", "--target", str(site)]
        subprocess.run(pip + [str(w) for w in sorted(wheels.glob("*.whl"))], check=True)
        env["PYTHONPATH"] = f"{site}:{ROOT}"
    else:
        env["PYTHONPATH"] = str(ROOT)
    cpu_only = dict(env, CUDA_VISIBLE_DEVICES="")
    py, cores = sys.executable, str(os.cpu_count() or 1)
    ds3d = [py, "-m", "ds3d.cli"]
    report: dict = {"started": time.strftime("%Y-%m-%dT%H:%M:%S"), "steps": {}}

    def step(name: str, command: list[str], limit: float, environment=env) -> None:
        """Runs `command` ("{json}" in it: OUT/NAME.json) for at most `limit` seconds."""
        json_out = out / f"{name}.json"
        command = [c.replace("{json}", str(json_out)) for c in command]
        start = time.perf_counter()
        rc: int | str
        with open(out / f"{name}.log", "w") as log:
            try:
                done = subprocess.run(
                    command,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    env=environment,
                    timeout=limit,
                    cwd=ROOT,
                )
                rc = done.returncode
            except subprocess.TimeoutExpired:
                rc = "timeout"
        report["steps"][name] = {
            "command": " ".join(command),
            "rc": rc,
            "seconds": round(time.perf_counter() - start, 1),
            "report": json.loads(json_out.read_text()) if json_out.is_file() else None,
            "log_tail": (out / f"{name}.log").read_text()[-3000:],
        }
        (out / "gpu_check.json").write_text(json.dumps(report, indent=1) + "\n")
        print(f"{name}: rc {rc}, {report['steps'][name]['seconds']} s", flush=True)

    tests = ["tests/fit", "tests/test_lifter.py", "tests/test_pipeline.py"]
    lift = [*ds3d, "bench", "lift", "--repeats", "3", "--out", "{json}"]
    pipeline = [*ds3d, "bench", "pipeline", "--repeats", "2", "--out", "{json}"]
    lsp = [*ds3d, "eval", "lsp", "--threads", cores, "--limit", "100", "--out", "{json}"]
    h36m = [*ds3d, "eval", "h36m", "--stride", "1", "--variants", "clean,noise10"]
    step("env", ["sh", "-c", f'nvidia-smi; {py} -c "{TORCH_INFO}"'], 30)
    step("tests", [py, "-m", "pytest", "-q", "-rs", "-k", "cuda", *tests], 150)
    step("lift_cuda", [*lift, "--device", "cuda", "--batch-sizes", "1,64,1024,8192"], 90)
    faiss = ["--set", "retrieval_on_device=false", "--batch-sizes", "1,1024,8192"]
    step("lift_cuda_faiss", [*lift, "--device", "cuda", *faiss], 90)
    step("pipeline_cuda", [*pipeline, "--device", "cuda", "--batch-sizes", "1,64"], 120)
    boxes = [*pipeline, "--device", "cuda", "--batch-sizes", "64", "--boxes"]
    step("pipeline_cuda_boxes", boxes, 60)
    half = str(max(1, int(cores) // 2))
    for name, workers, threads, batches in (
        ("2", "1", "2", "16"),
        ("all", "1", cores, "16,64"),
        ("workers", half, "2", "16,64"),
    ):
        command = [*pipeline, "--device", "cpu", "--workers", workers, "--threads", threads]
        step(f"pipeline_cpu_{name}", [*command, "--batch-sizes", batches], 90, cpu_only)
    for device, environment in (("cuda", env), ("cpu", cpu_only)):
        step(f"eval_lsp_{device}", [*lsp, "--device", device], 90, environment)
        step(f"eval_h36m_{device}", [*h36m, "--device", device, "--out", "{json}"], 60, environment)
    _serve(step, env, out)
    step("profile", [py, "-m", "tools.gpu_profile", "--out", "{json}"], 60)
    return report


def _serve(step, env: dict, out: Path) -> None:
    """ds3d-serve on CUDA in the background while the load tests run against it."""
    server_env = dict(env, DS3D_DEVICE="cuda", DS3D_PORT=str(PORT), DS3D_MAX_BATCH_SIZE="64")
    server_env |= {"DS3D_MAX_QUEUE": "512", "DS3D_MAX_LIFT_BATCH_SIZE": "1024"}
    with open(out / "server.log", "w") as log:
        server = subprocess.Popen(
            [sys.executable, "-m", "ds3d_service"],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=server_env,
            cwd=ROOT,
        )
    url = f"http://127.0.0.1:{PORT}"
    try:
        for _ in range(120):
            try:
                urllib.request.urlopen(url + "/readyz", timeout=2)
                break
            except OSError:
                if server.poll() is not None:
                    return  # it did not start: server.log says why
                time.sleep(1)
        poses = out / "lsp_poses.json"  # LSP's annotated poses, as `ds3d lift` reads them
        subprocess.run([sys.executable, "-c", LSP_POSES, str(poses)], env=env, check=False)
        images = str(Path(env.get("DS3D_DATA", ROOT.parent / "shared" / "data")) / "lsp" / "images")
        load = [sys.executable, "-m", "tools.loadtest", url, "--mode", "closed", "--duration", "20"]
        load += ["--out", str(out), "--deadline", "10", "--concurrency", "64"]
        step(
            "serve_pose",
            [*load, "--endpoint", "pose", "--images", images, "--name", "serve_pose"],
            60,
        )
        lift = [*load, "--endpoint", "lift", "--poses", str(poses), "--items", "64"]
        step("serve_lift", [*lift, "--name", "serve_lift"], 60)
    finally:
        server.terminate()
        server.wait(30)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    verbs = parser.add_subparsers(dest="verb", required=True)
    p = verbs.add_parser("pack", help="the data subset (and wheels) for a bare GPU machine")
    p.add_argument("out", type=Path)
    p.add_argument("--images", type=int, default=200, help="LSP test images")
    p.add_argument("--wheels", action="store_true", help="also the wheels PyTorch images lack")
    p = verbs.add_parser("run", help="every step, then OUT/gpu_check.json")
    p.add_argument("out", type=Path)
    p.add_argument("--data", type=Path, help="DS3D_DATA for the steps (default: as set)")
    p.add_argument("--wheels", type=Path, help="a folder of wheels to install first")
    args = parser.parse_args(argv)
    if args.verb == "pack":
        pack(args.out, args.images, args.wheels)
    else:
        run(args.out, args.data, args.wheels)
    return 0


if __name__ == "__main__":
    sys.exit(main())
