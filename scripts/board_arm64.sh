#!/usr/bin/env bash
# The device on arm64 with Debian stable's own packages, under user-mode emulation: an arm64
# Debian 13 ("trixie") root filesystem (debootstrap, second stage through qemu-aarch64-static),
# inside it exactly the board's install route of docs/board-install.md, then
#   1. the device-only tests (those of scripts/board_versions.sh, test_flash_edges.py,
#      test_image_transfer.py and test_layers.py's packet tests: they import protocol and
#      device_runtime, nothing of the host's stack);
#   2. frames: this checkout's host (x86 .venv) renders and fits the tooth and the built-in
#      head at 64 and 128 px, with and without depth, and provisions each into an arm64
#      device process over TCP; the arm64 device's standalone frames (--frames) are compared
#      with `eigencast view` here (pixels that differ, largest difference); then the served
#      path: an x86 `eigencast serve` drives the arm64 device resting on a view until its
#      exact frame, which must equal the x86 ray-cast bit for bit;
#   3. benchmarks/bench_board.py on arm64 (S=1, standalone, one trace): it runs. Emulation is
#      no speed figure: no time printed here says anything about a board.
#
#   sudo scripts/board_arm64.sh [ROOT]   (from the repository root, .venv built)
#
# ROOT (default /var/tmp/eigencast-arm64-root) is built once (debootstrap and apt: ~30 min on
# 2 cores) and reused: any finished Debian root there is taken as it is, apt runs only for a
# missing package; WORK (ROOT/opt/work) is made anew. Needs root (debootstrap,
# chroot, binfmt_misc), the packages qemu-user-static, debootstrap and binfmt-support
# (apt-get install qemu-user-static debootstrap binfmt-support), and Debian's package mirrors
# (MIRROR, default http://deb.debian.org/debian). The repository goes in as `git archive
# HEAD` (committed files only). Exit status: 0 when every step passed.
#
#   STEPS="frames bench" ...   run only those of the steps tests, frames, bench
#   FRAMES="tooth-64-depth head-128-depth" SERVED="tooth-64-depth" ...   fewer images
#   REUSE=1 ...                keep the arm64 install and WORK/x86 (renders, fits) of an earlier
#                              run when protocol, device_runtime, host, tests, benchmarks and
#                              pyproject.toml are unchanged since (the install route then is
#                              not run again)
set -euo pipefail
ROOT=$(realpath -m "${1:-/var/tmp/eigencast-arm64-root}")
WORK_IN=/opt/work                        # WORK as the arm64 side sees it
WORK="$ROOT$WORK_IN"
[ $# -ge 2 ] && { echo "board_arm64.sh: WORK is always ROOT$WORK_IN (the chroot must see it)" >&2
                  exit 2; }
MIRROR=${MIRROR:-http://deb.debian.org/debian}
HOSTPY=${HOSTPY:-.venv/bin/python}
STEPS=${STEPS:-tests frames bench}      # which of the three steps run
want() { case " $STEPS " in *" $1 "*) return 0 ;; esac; return 1; }
SUITE=trixie
BOARD_PKGS="python3-numpy python3-serial python3-cbor2 python3-zstandard python3-pygame \
python3-venv python3-setuptools"        # docs/board-install.md, word for word
TEST_PKGS="python3-pytest python3-hypothesis python3-pil"   # test tools, not the device's
VIEWS="12.5,3;100,-44;250,20;33,61;301,-12"

die() { echo "board_arm64.sh: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || die "needs root (debootstrap, chroot, binfmt_misc): run it with sudo"
[ -x "$HOSTPY" ] && [ -f pyproject.toml ] || die "run it from the repository root after make venv"
for c in debootstrap qemu-aarch64-static update-binfmts git; do
    command -v "$c" >/dev/null || die "$c missing: apt-get install qemu-user-static debootstrap binfmt-support"
done

# arm64 binaries must run through qemu: binfmt_misc, registered with the F flag (the
# interpreter opened at registration, so it works inside the chroot too)
if [ ! -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ]; then
    [ -e /proc/sys/fs/binfmt_misc/register ] ||
        mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc 2>/dev/null || true
    update-binfmts --enable qemu-aarch64 2>/dev/null || true
fi
[ -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ] ||
    die "cannot register qemu-aarch64 with binfmt_misc (a container without it?): apt and pip spawn arm64 children, which only binfmt_misc runs"

IN_ROOT=(nice chroot "$ROOT" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root
         LANG=C.UTF-8 SDL_VIDEODRIVER=dummy OPENBLAS_NUM_THREADS=1 PYTHONUNBUFFERED=1)
in_root() { "${IN_ROOT[@]}" "$@"; }
cleanup() {
    [ -n "${DEVPID:-}" ] && kill "$DEVPID" 2>/dev/null && wait "$DEVPID" 2>/dev/null
    [ -n "${SERVEPID:-}" ] && kill "$SERVEPID" 2>/dev/null && wait "$SERVEPID" 2>/dev/null
    [ -n "${MOUNTED_PTS:-}" ] && umount "$ROOT/dev/pts"  # only mounts of this run's
    [ -n "${MOUNTED_PROC:-}" ] && umount "$ROOT/proc"
    true
}
trap cleanup EXIT
t0=$SECONDS
stamp() { echo "== $* ($((SECONDS - t0)) s)"; }

# ---------------------------------------------------------------- the root filesystem
# a finished debootstrap leaves apt-get and removes its own /debootstrap folder: such a root is
# reused whoever built it; anything else at ROOT that is not empty is not ours to delete
if [ ! -x "$ROOT/usr/bin/apt-get" ] || [ -e "$ROOT/debootstrap" ]; then
    [ -z "$(ls -A "$ROOT" 2>/dev/null)" ] || [ -e "$ROOT/debootstrap" ] ||
        die "$ROOT is neither empty nor an unfinished debootstrap: give another ROOT"
    stamp "debootstrap $SUITE arm64 into $ROOT"
    rm -rf "$ROOT" && mkdir -p "$ROOT"
    nice debootstrap --arch=arm64 --foreign --variant=minbase "$SUITE" "$ROOT" "$MIRROR"
    cp "$(command -v qemu-aarch64-static)" "$ROOT/usr/bin/"
    nice chroot "$ROOT" /debootstrap/debootstrap --second-stage
    printf 'deb %s %s main\ndeb %s %s-updates main\ndeb %s-security %s-security main\n' \
        "$MIRROR" $SUITE "$MIRROR" $SUITE "${MIRROR%/debian}/debian-security" $SUITE \
        >"$ROOT/etc/apt/sources.list"
fi
cp /etc/resolv.conf "$ROOT/etc/resolv.conf"
mountpoint -q "$ROOT/proc" || { mount -t proc proc "$ROOT/proc" && MOUNTED_PROC=1; }
# pseudo-terminals (the tests' serial lines are pty pairs): the host's, whose slaves then
# exist in the root too
mountpoint -q "$ROOT/dev/pts" || { mount --bind /dev/pts "$ROOT/dev/pts" && MOUNTED_PTS=1; }
# apt runs only when a package is missing (dpkg's own record, not a mark of this script's)
installed() { in_root dpkg-query -W -f '${db:Status-Abbrev}\n' "$@" 2>/dev/null | grep -c '^ii'; }
if [ "$(installed $BOARD_PKGS $TEST_PKGS)" != "$(echo $BOARD_PKGS $TEST_PKGS | wc -w)" ]; then
    stamp "the board's packages: apt install $BOARD_PKGS"
    in_root DEBIAN_FRONTEND=noninteractive apt-get update -q
    # what the board runs (sudo apt install ...), recommends and all
    in_root DEBIAN_FRONTEND=noninteractive apt-get install -y -q $BOARD_PKGS
    in_root DEBIAN_FRONTEND=noninteractive apt-get install -y -q $TEST_PKGS
fi
in_root dpkg-query -W -f '${Package} ${Version}\n' python3 $BOARD_PKGS $TEST_PKGS

# ---------------------------------------------------------------- the board's install route
# what the arm64 side runs: the packages, the tests and the benchmarks as committed
TREE=$(git rev-parse HEAD:protocol HEAD:device_runtime HEAD:host HEAD:tests HEAD:benchmarks \
       HEAD:pyproject.toml | sha1sum | cut -c1-16)
if [ "$(cat "$ROOT/opt/eigencast/.eigencast-tree" 2>/dev/null)" = "$TREE" ] &&
   [ -n "${REUSE:-}" ]; then
    stamp "REUSE: eigencast already installed from these files ($TREE); WORK/x86 kept"
    if want tests; then rm -rf "$WORK/tests-run"; fi
    find "$WORK" -mindepth 1 -maxdepth 1 ! -name x86 ! -name tests-run -exec rm -rf {} +
    mkdir -p "$WORK/tests-run"
else
    stamp "eigencast into an arm64 venv (--system-site-packages; pip --no-index --no-build-isolation)"
    rm -rf "$ROOT/opt/eigencast" "$ROOT/opt/eigencast-env" "$WORK"
    mkdir -p "$ROOT/opt/eigencast" "$WORK/tests-run"
    git archive HEAD | tar -x -C "$ROOT/opt/eigencast"
    in_root python3 -m venv --system-site-packages /opt/eigencast-env
    in_root /opt/eigencast-env/bin/pip install --quiet --no-index --no-build-isolation \
        '/opt/eigencast[device]'
    echo "$TREE" >"$ROOT/opt/eigencast/.eigencast-tree"
    in_root /opt/eigencast-env/bin/eigencast-device --version
    in_root uname -m
fi

# ---------------------------------------------------------------- 1. device-only tests
# the tests run from a copy (no pyproject.toml): they import the installed package
want tests && cp -r "$ROOT/opt/eigencast/tests" "$ROOT/opt/eigencast/docs" "$WORK/tests-run/"
TESTS="tests/test_framing.py tests/test_messages.py tests/test_records.py tests/test_scores.py
    tests/test_reconstruct.py tests/test_orbit.py tests/test_image_writer.py tests/test_flash.py
    tests/test_wire_errors.py tests/test_display.py tests/test_auth.py tests/test_link.py
    tests/test_transport.py tests/test_image_receiver.py tests/test_golden.py
    tests/test_host_session.py tests/test_device_fuzz.py tests/test_layers.py
    tests/test_flash_edges.py tests/test_image_transfer.py"
tests_rc=0
if want tests; then
stamp "device-only tests on arm64"
in_root sh -c "cd $WORK_IN/tests-run && timeout 7200 /opt/eigencast-env/bin/python -m pytest \
    -q -p no:cacheprovider --durations=8 $(echo $TESTS) \
    -k 'not a_device_drops_every_bad_layer'" || tests_rc=$?
# (test_layers.py's last test builds its image with the host's fit: numba, not on a board)
stamp "device-only tests: exit $tests_rc"
fi

# ---------------------------------------------------------------- 2. frames against x86
stamp "x86: render, fit"
mkdir -p "$WORK/x86"
[ -f "$WORK/x86/k.key" ] || "$HOSTPY" -m host.cli keygen -o "$WORK/x86/k.key" >/dev/null
MODELS=()
for vol in tooth head; do
    for size in 64 128; do
        cell=$([ "$size" = 64 ] && echo 16 || echo 32)
        [ -d "$WORK/x86/$vol-$size.cdb" ] || nice "$HOSTPY" -m host.cli render "builtin:$vol" -o "$WORK/x86/$vol-$size.cdb" \
            --views grid:24x6 --size "$size" >/dev/null 2>&1
        for depth in depth no-depth; do
            [ -f "$WORK/x86/$vol-$size-$depth.ecs" ] || nice "$HOSTPY" -m host.cli fit "$WORK/x86/$vol-$size.cdb" \
                -o "$WORK/x86/$vol-$size-$depth.ecs" --cell "$cell" --key "$WORK/x86/k.key" \
                --"$depth" --no-cache >/dev/null 2>&1
            MODELS+=("$vol-$size-$depth")
        done
    done
done

start_device() {  # an arm64 device process on TCP; sets DEVPID and PORT
    local log=$1; shift
    # (not through a function: $! must be the device, which nice and chroot exec)
    "${IN_ROOT[@]}" /opt/eigencast-env/bin/eigencast-device --listen 127.0.0.1:0 \
        --key "$WORK_IN/x86/k.key" "$@" 2>"$log" &
    DEVPID=$!
    PORT=
    local until=$((SECONDS + ${START_S:-1200}))  # a loaded emulation: minutes to start
    while [ $SECONDS -lt $until ]; do
        PORT=$(sed -n 's/.*listening on tcp-listen:\/\/127.0.0.1:\([0-9]*\).*/\1/p' "$log")
        [ -n "$PORT" ] && return 0
        kill -0 "$DEVPID" 2>/dev/null || break
        sleep 1
    done
    cat "$log" >&2; die "the arm64 device did not start"
}
stop_device() { kill -INT "$DEVPID" && wait "$DEVPID" || true; DEVPID=; }

frames_rc=0
# FRAMES: the images whose arm64 frames are compared (default all eight; under a loaded
# emulation each takes minutes: a device process starts twice)
[ -n "${FRAMES:-}" ] && read -r -a MODELS <<<"$FRAMES"
want frames || MODELS=()
for name in "${MODELS[@]}"; do
    stamp "$name: provision the arm64 device, its standalone frames"
    flash="$WORK/flash-$name"
    start_device "$WORK/device-$name.log" --flash "$WORK_IN/flash-$name" --headless
    "$HOSTPY" -m host.cli provision "$WORK/x86/$name.ecs" --port "socket://127.0.0.1:$PORT" \
        --key "$WORK/x86/k.key" --quiet
    stop_device
    in_root /opt/eigencast-env/bin/eigencast-device --standalone --flash "$WORK_IN/flash-$name" \
        --key "$WORK_IN/x86/k.key" --headless --frames "$WORK_IN/frames-$name" \
        --views "$VIEWS" 2>/dev/null
    "$HOSTPY" - "$WORK" "$name" <<'PY' || frames_rc=1
import csv, subprocess, sys
from pathlib import Path
import numpy as np
from PIL import Image
work, name = Path(sys.argv[1]), sys.argv[2]
rows = list(csv.DictReader(open(work / f"frames-{name}" / "frames.csv")))
# every frame shown: a view's blend (`view --blend`), then, with depth, its warp (`view`)
worst, total, by1, by8, over8 = 0, 0, 0, 0, 0
for r in rows:
    out = work / "view.png"
    subprocess.run([sys.executable, "-m", "host.cli", "view", str(work / "x86" / f"{name}.ecs"),
                    "--phi", r["phi_deg"], "--theta", r["theta_deg"], "-o", str(out)]
                   + (["--blend"] if r["kind"] == "blend" else []),
                   check=True, capture_output=True)
    a = np.asarray(Image.open(out)).astype(int)
    b = np.asarray(Image.open(work / f"frames-{name}" / r["file"])).astype(int)
    d = np.abs(a - b).max(axis=-1)  # per pixel, over its channels
    worst, total = max(worst, int(d.max())), total + d.size
    by1, by8, over8 = by1 + int((d == 1).sum()), by8 + int(((d > 1) & (d <= 8)).sum()), \
        over8 + int((d > 8).sum())
# docs/protocol.md ("Host and device on different CPUs"): the own frames of two CPUs may
# differ by float32 rounding, "a level off on a few pixels"; the tests model another CPU as
# a level off on a tenth of the pixels and up to 8 on one in a hundred (tests/test_correction.py,
# tests/test_rest_exact.py). Within that: <= 10 % off by one, <= 1 % by 2..8, none by more.
within = by1 <= 0.10 * total and by8 <= 0.01 * total and over8 == 0
kinds = sorted({r["kind"] for r in rows})
print(f"{name}: {len(rows)} arm64 standalone frames ({'/'.join(kinds)}) vs x86 `eigencast view`: "
      f"{by1 + by8 + over8} of {total} pixels differ ({by1} by 1, {by8} by 2-8, {over8} by "
      f"more), largest {worst}: {'within' if within else 'OUTSIDE'} the bound")
sys.exit(0 if len(rows) >= 6 and within else 1)
PY
done

# SERVED: the provisioned images of FRAMES that are also served to an exact frame
SERVED=${SERVED:-"tooth-64-depth head-128-depth head-64-no-depth"}
for name in $SERVED; do
    case " ${MODELS[*]} " in *" $name "*) ;; *) die "SERVED $name is not in FRAMES" ;; esac
done
want frames || SERVED=
for name in $SERVED; do
    stamp "$name: served, x86 host -> arm64 device resting on 120,15 until its exact frame"
    rm -rf "$WORK/served-$name"
    start_device "$WORK/device-served-$name.log" --flash "$WORK_IN/flash-$name" --headless \
        --frames "$WORK_IN/served-$name" --view 120,15
    "$HOSTPY" -m host.cli serve "$WORK/x86/$name.ecs" --port "socket://127.0.0.1:$PORT" \
        --key "$WORK/x86/k.key" --quiet --duration 900 &
    SERVEPID=$!
    got=
    while kill -0 "$SERVEPID" 2>/dev/null; do   # serve ends itself after --duration
        grep -q ',exact$' "$WORK/served-$name/frames.csv" 2>/dev/null && { got=1; break; }
        sleep 1
    done
    kill -INT "$SERVEPID" 2>/dev/null; wait "$SERVEPID" || true; SERVEPID=
    stop_device
    [ -n "$got" ] || { echo "$name: no exact frame" >&2; frames_rc=1; continue; }
    "$HOSTPY" - "$WORK" "$name" <<'PY' || frames_rc=1
import csv, sys
from pathlib import Path
import numpy as np
from PIL import Image
from host.fit.model import HostModel
from host.link.true_views import open_true_view_scores
from protocol.keys import load_key
work, name = Path(sys.argv[1]), sys.argv[2]
rows = list(csv.DictReader(open(work / f"served-{name}" / "frames.csv")))
row = [r for r in rows if r["kind"] == "exact"][-1]
view = (float(row["phi_deg"]), float(row["theta_deg"]))
model = HostModel.load(work / "x86" / f"{name}.ecs", key=load_key(work / "x86" / "k.key"))
truth = open_true_view_scores(model).renderer.render(*view)[0]
got = np.asarray(Image.open(work / f"served-{name}" / row["file"]))
same = got.shape == truth.shape and bool((got == truth).all())
kinds = sorted({r["kind"] for r in rows})
print(f"{name}: arm64 exact frame of {view} {'equals' if same else 'DIFFERS FROM'} the x86 "
      f"ray-cast bit for bit ({len(rows)} frames shown, kinds {kinds})")
sys.exit(0 if same else 1)
PY
done
stamp "frames: exit $frames_rc"

# ---------------------------------------------------------------- 3. bench_board.py runs
bench_rc=0
if want bench; then
stamp "bench_board.py on arm64 (S=1, standalone, trace rest): it runs; no speed figure"
# the flash is provisioned here (x86 host) where bench_board.py looks for it (the folder
# name and its .done mark); on the board side the benchmark then needs no host
"$HOSTPY" - "$WORK" <<'PY'
import sys
from pathlib import Path
sys.path.insert(0, "benchmarks")
from link_real import provisioned_flash
work = Path(sys.argv[1])
provisioned_flash(work / "x86" / "tooth-64-depth.ecs", work / "bench")
PY
# bench_board.py pins its device threads to core 0; here they stay on the cores this script
# was given (the shared machine's rule: core 1), so the pinning is switched off
in_root sh -c "cd /opt/eigencast && timeout 1800 /opt/eigencast-env/bin/python -c '
import os, runpy, sys
os.sched_setaffinity = lambda pid, cores: None
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name=\"__main__\")' \
    benchmarks/bench_board.py $WORK_IN/x86/tooth-64-depth.ecs --slowdown 1 \
    --links standalone --traces rest --work $WORK_IN/bench" || bench_rc=$?
stamp "bench_board.py: exit $bench_rc"
fi

echo "tests $tests_rc, frames $frames_rc, bench $bench_rc"
[ "$tests_rc" = 0 ] && [ "$frames_rc" = 0 ] && [ "$bench_rc" = 0 ]
