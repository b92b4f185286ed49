#!/usr/bin/env bash
# The wheels a device batch installs, small enough to carry: .whl/ (made by ../shared/device/make-wheels.sh)
# copied into DIR (default runs/whl-train, git-ignored) without pyopengl (training never imports OpenGL), with
# mujoco-mjx's test models (mujoco/mjx/test_data, ~6.5 MB compressed) dropped from its wheel and MuJoCo Studio's
# GUI (mujoco/experimental, ~15.7 MB: neither mujoco, mjx, dm_control nor lnnmpc imports it; checked on the CPU
# with the import blocked; walker runs installed and trained from it on an H200) from mujoco's, since the device
# tool refuses a working tree over 64 MiB and the tracked files plus the whole wheels passed it.
#
#   experiments/scripts/train_wheels.sh [DIR]
#
# Then carry DIR and install from DIR/*.whl (pip --no-deps; the dropped files are not imported).
set -eu
dir=${1:-runs/whl-train}
python=${PYTHON:-python3}
ls .whl/*.whl >/dev/null  # fails with a message when make-wheels.sh has not been run
rm -rf "$dir"
mkdir -p "$dir"
cp .whl/*.whl "$dir"/
rm -f "$dir"/pyopengl-*.whl
for wheel in "$dir"/mujoco_mjx-*.whl "$dir"/mujoco-*.whl; do
    "$python" - "$wheel" <<'PY'
import os
import sys
import zipfile

path = sys.argv[1]
dropped = ("mujoco/mjx/test_data/", "mujoco/experimental/")
with zipfile.ZipFile(path) as source, zipfile.ZipFile(path + ".tmp", "w", zipfile.ZIP_DEFLATED) as target:
    for info in source.infolist():
        if not info.filename.startswith(dropped):
            target.writestr(info, source.read(info.filename))
os.replace(path + ".tmp", path)
PY
done
echo "$dir: $(ls "$dir" | wc -l) wheels, $(du -sh "$dir" | cut -f1)"
