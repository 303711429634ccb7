#!/usr/bin/env bash
# The device side on the oldest versions it claims (Debian stable's own packages, see
# docs/board-install.md): a virtual environment with exactly those versions from PyPI, the
# board's install command (no index, no build isolation: every requirement must already be
# satisfied), the device-only tests, and a real device process of that environment showing
# frames that must equal this checkout's `eigencast view` bit for bit.
#
#   scripts/board_versions.sh [WORK_DIR]      (needs PyPI once; ~2 minutes)
#   PINS="numpy==1.26.0 ..." scripts/board_versions.sh    (other versions, e.g. the bounds)
#
# Run it from the repository root with .venv built (make venv): the host side of the check
# (fit, provision, view) runs there.
set -euo pipefail
WORK=${1:-/tmp/eigencast-board}
HOSTPY=${HOSTPY:-.venv/bin/python}
PINS=${PINS:-"numpy==2.2.0 pyserial==3.5 cbor2==5.6.0 zstandard==0.23.0 pygame==2.6.0"}
rm -rf "$WORK" && mkdir -p "$WORK"
python3 -m venv "$WORK/env"
# setuptools: the oldest build-system.requires allows; pytest, hypothesis and pillow (to read
# the PNGs the tests write) are test tools, not device dependencies
"$WORK/env/bin/pip" install --quiet $PINS setuptools==77.0.3 pytest pytest-timeout hypothesis \
    pillow
# the board's command: everything must already be there
"$WORK/env/bin/pip" install --quiet --no-index --no-build-isolation ".[device]"
"$WORK/env/bin/pip" list 2>/dev/null | grep -Ei '^(numpy|pyserial|cbor2|zstandard|pygame) '
"$WORK/env/bin/eigencast-device" --version
# device-only tests (they import protocol and device_runtime, nothing of the host's stack)
cp -r tests docs "$WORK/"
(cd "$WORK" && SDL_VIDEODRIVER=dummy env/bin/python -m pytest -q -p no:cacheprovider \
    tests/test_framing.py tests/test_messages.py tests/test_records.py tests/test_scores.py \
    tests/test_reconstruct.py tests/test_orbit.py tests/test_image_writer.py \
    tests/test_flash.py tests/test_wire_errors.py tests/test_display.py tests/test_auth.py \
    tests/test_link.py tests/test_transport.py tests/test_image_receiver.py \
    tests/test_golden.py tests/test_host_session.py tests/test_device_fuzz.py 2>&1 | tail -1)
# a real device process of the pinned environment: provisioned by this checkout's host,
# then standalone, its frames against `eigencast view`
"$HOSTPY" -m host.cli render builtin:tooth -o "$WORK/t.cdb" --views grid:24x6 --size 64 \
    --samples 120 2>/dev/null
"$HOSTPY" -m host.cli keygen -o "$WORK/k.key" >/dev/null
for depth in --no-depth --depth; do
    rm -rf "$WORK/flash" "$WORK/frames"
    "$HOSTPY" -m host.cli fit "$WORK/t.cdb" -o "$WORK/t.ecs" --cell 16 --key "$WORK/k.key" \
        $depth >/dev/null 2>&1
    "$WORK/env/bin/eigencast-device" --flash "$WORK/flash" --key "$WORK/k.key" \
        --listen 127.0.0.1:0 --headless 2>"$WORK/device.log" &
    pid=$!
    for _ in $(seq 100); do grep -q "listening on" "$WORK/device.log" && break; sleep 0.1; done
    port=$(sed -n 's/.*listening on tcp-listen:\/\/127.0.0.1:\([0-9]*\).*/\1/p' "$WORK/device.log")
    "$HOSTPY" -m host.cli provision "$WORK/t.ecs" --port "socket://127.0.0.1:$port" \
        --key "$WORK/k.key" --quiet
    kill -INT $pid && wait $pid
    "$WORK/env/bin/eigencast-device" --standalone --flash "$WORK/flash" --key "$WORK/k.key" \
        --headless --frames "$WORK/frames" --views "12.5,3;100,-44;250,20" 2>/dev/null
    "$HOSTPY" - "$WORK" "$depth" <<'PY'
import csv, subprocess, sys
from pathlib import Path
import numpy as np
from PIL import Image
work, depth = Path(sys.argv[1]), sys.argv[2]
rows = list(csv.DictReader(open(work / "frames" / "frames.csv")))
worst = 0
for r in rows:
    out = work / "view.png"
    subprocess.run([sys.executable, "-m", "host.cli", "view", str(work / "t.ecs"), "--phi",
                    r["phi_deg"], "--theta", r["theta_deg"], "-o", str(out)], check=True,
                   capture_output=True)
    a = np.asarray(Image.open(out)).astype(int)
    b = np.asarray(Image.open(work / "frames" / r["file"])).astype(int)
    worst = max(worst, int(np.abs(a - b).max()))
print(f"{depth}: {len(rows)} device frames, largest difference from eigencast view: {worst}")
sys.exit(1 if worst else 0)
PY
done
