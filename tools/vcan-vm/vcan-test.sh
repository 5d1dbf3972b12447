#!/usr/bin/env bash
# `make vcan-test`: the vcan-marked tests (tests/vcan), the multi-process demo on socketcan:vcan0
# among them. Runs them directly when this machine has vcan0, otherwise
# inside the vcan VM (tools/vcan-vm/run, which shares this repository writable with the guest and
# calls this same script there). Exits non-zero when anything fails, and also when vcan0 is missing
# where it must exist (PVT_REQUIRE_VCAN=1: a broken VM must not pass by skipping every test).
# Environment: VCAN_VM_TIMEOUT (host seconds for the whole VM run, default 900), VCAN_VM_CLOCK (the
# VM's clock, see tools/vcan-vm/run --help), PYTEST_ADDOPTS for
# extra pytest options.
set -euo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(cd "$here/../.." && pwd)
cd "$repo"
py=$repo/.venv/bin/python
channel=${PVT_VCAN_CHANNEL:-vcan0}

has_vcan() { [ -e "/sys/class/net/$channel" ]; }

if ! has_vcan; then
  if [ "${VCAN_VM_GUEST:-}" = 1 ]; then
    echo "vcan-test: inside the VM but $channel is missing" >&2; exit 125
  fi
  [ -x "$py" ] || { echo "vcan-test: no $py (run make test first)" >&2; exit 2; }
  # The planner's kernels (planner/jit.py) are compiled for the CPU they run on, and the VM's emulated
  # CPU is not this one: compiled there, under emulation, they took minutes and the demos timed out.
  # Compiled here for a generic x86-64 CPU, into the same cache the guest reads, they load there at once.
  # The guest's one emulated CPU saturates: three Python processes (the cycle engine, the master, the drives)
  # drained the FIFOs there (FIFO down to 2, BUS_OVERLOAD) and starved the drives (TPDO_TIMEOUT). In the VM the
  # master sends SYNC and its frames itself (PVT_ENGINE=0: the kernel's broadcast manager for SYNC, as before
  # the engine) and the drives run best-effort (PVT_DRIVES_PRIORITY=0). The VM proves function on SocketCAN,
  # not timing; the engine's function is tested on the ipc bus (tests/bus/test_engine.py, the realtime tests).
  echo "vcan-test: compiling the planner's kernels for the VM's generic CPU"
  NUMBA_CPU_NAME=generic "$py" -c 'from planner.plan import warm_up; warm_up()'
  echo "vcan-test: no $channel on this machine, running in the vcan VM"
  exec "$here/run" --share "$repo" --timeout "${VCAN_VM_TIMEOUT:-900}" \
    --env "PYTEST_ADDOPTS=${PYTEST_ADDOPTS:-}" --env NUMBA_CPU_NAME=generic \
    --env "PVT_VCAN_CHANNEL=$channel" --env PVT_DRIVES_PRIORITY=0 --env PVT_ENGINE=0 -- "$here/vcan-test.sh"
fi

export PVT_REQUIRE_VCAN=1 PVT_VCAN_CHANNEL=$channel
status=0
start=$(date +%s)
# no pytest cache writes and no .pyc files in the (shared) work tree; the cache lives in /tmp in the VM
"$py" -m pytest -q -p no:cacheprovider -m vcan tests/vcan || status=$?
echo "vcan-test: tests/vcan exit $status after $(( $(date +%s) - start )) s"
# The multi-process demo on socketcan (pvt demo --bus socketcan:vcan0, drives in a second process)
# is tests/vcan/test_vcan_demo.py, part of the run above.
exit $status
