#!/usr/bin/env bash
# Peer libraries for the benchmarks, each in its own virtual environment under
# benchmarks/.envs/ (git-ignored). aniposelib pulls opencv-contrib-python, which would
# overwrite the project's headless OpenCV, so it never goes into the project's venv.
#
#   bash benchmarks/setup_peers.sh        # then: python benchmarks/bench_reconstruct.py
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
envs="$here/.envs"
python="${PYTHON:-python3}"

mkdir -p "$envs"
if [ ! -x "$envs/aniposelib/bin/python" ]; then
    "$python" -m venv "$envs/aniposelib"
fi
"$envs/aniposelib/bin/python" -m pip install --quiet --upgrade pip
"$envs/aniposelib/bin/python" -m pip install --quiet "aniposelib>=0.5,<0.6" "numpy<2.3"
"$envs/aniposelib/bin/python" -c "import aniposelib, cv2; print('aniposelib', aniposelib.__version__ if hasattr(aniposelib, '__version__') else '?', 'cv2', cv2.__version__)"
