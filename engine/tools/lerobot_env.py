"""Shared bootstrap for the engine's LeRobot tools: a pinned venv at the repository root.

`ensure_venv()` re-executes the calling script inside `<repo>/.venv-lerobot` (Python 3.12, which
LeRobot 0.6.1 requires), creating the venv and installing the pinned requirements first when
they are missing. The venv is gitignored; CI never runs these tools.
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# KAIROS_LEROBOT_VENV names an existing venv with the pinned requirements (e.g. one shared by
# several checkouts); the default is `<repo>/.venv-lerobot`.
VENV = Path(os.environ.get("KAIROS_LEROBOT_VENV") or REPO / ".venv-lerobot")
# `lerobot[smolvla,pi]` (SmolVLA, π0 and π0.5) pulls torch from PyPI, whose Linux wheel links the
# CUDA runtime (about 4 GB of nvidia-* wheels); it still runs on CPU, which is all these tools use.
REQUIREMENTS = ["lerobot[smolvla,pi]==0.6.1", "safetensors>=0.4.3"]


def _python312() -> str:
    candidates = []
    pyenv = shutil.which("pyenv")
    if pyenv:
        root = subprocess.run([pyenv, "root"], capture_output=True, text=True, check=False).stdout.strip()
        if root:
            candidates += sorted(Path(root, "versions").glob("3.12*/bin/python3.12"), reverse=True)
    found = shutil.which("python3.12")
    if found:
        candidates.append(Path(found))
    for c in candidates:
        if Path(c).exists():
            return str(c)
    sys.exit("LeRobot 0.6.1 needs Python 3.12: install it (e.g. `pyenv install 3.12`) and retry")


def _venv_ready(python: Path) -> bool:
    if not python.exists():
        return False
    probe = "import lerobot, torch, transformers, safetensors; assert lerobot.__version__ == '0.6.1'"
    return subprocess.run([str(python), "-c", probe], capture_output=True, check=False).returncode == 0


def ensure_venv() -> None:
    """Re-exec this script in the pinned venv, building the venv if needed."""
    python = VENV / "bin" / "python"
    if Path(sys.prefix).resolve() == VENV.resolve():
        return
    if not _venv_ready(python):
        if not python.exists():
            print(f"creating {VENV} ...", flush=True)
            subprocess.run([_python312(), "-m", "venv", str(VENV)], check=True)
        print(f"installing {' '.join(REQUIREMENTS)} into {VENV} (several GB, once) ...", flush=True)
        subprocess.run([str(python), "-m", "pip", "install", *REQUIREMENTS], check=True)
    os.execv(str(python), [str(python), *sys.argv])
