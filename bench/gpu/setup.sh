#!/usr/bin/env bash
# Installs gscompress and gsplat on a CUDA machine without network access, from files carried in
# the working tree, and builds gsplat's CUDA kernels against the torch found there.
#
#   bash bench/gpu/setup.sh              # on the GPU machine (bench/gpu/wheels filled beforehand
#                                        # by bench/gpu/fetch_wheels.sh and carried)
#   bash bench/gpu/setup.sh --cpu-smoke  # the same steps without CUDA and the kernel build
#
# The venv (GSC_GPU_BUILD/venv) sees the machine's own packages (torch, numpy, ...) through a .pth
# file and holds only what they lack: the carried wheels and gscompress (editable). gsplat
# compiles its kernels on first use (setup.md: about 80 s on an H100 for one architecture);
# they are built here, once, into GSC_GPU_BUILD/torch_extensions, for the GPU's architecture
# only. Every step prints its seconds; a missing file, CUDA toolkit or GPU stops the script with
# one line. A second run on the same machine (GSC_GPU_BUILD kept) takes seconds.
#
# Writes GSC_GPU_BUILD/env.sh (the variables later steps need: source it) and OUT/setup.json.
# Environment: GSC_GPU_PYTHON (python3: the interpreter whose torch is used), GSC_GPU_WHEELS
# (bench/gpu/wheels), GSC_GPU_BUILD (bench/gpu/.build), OUT (bench_out/gpu).
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
smoke=0
case ${1:-} in
    --cpu-smoke) smoke=1 ;;
    "") ;;
    *) echo "usage: setup.sh [--cpu-smoke]" >&2; exit 2 ;;
esac
python=${GSC_GPU_PYTHON:-python3}
wheels=${GSC_GPU_WHEELS:-$root/bench/gpu/wheels}
build=${GSC_GPU_BUILD:-$root/bench/gpu/.build}
out=${OUT:-$root/bench_out/gpu}
venv=$build/venv
vpy=$venv/bin/python
mkdir -p "$build" "$out"

fail() { echo "setup.sh: $*" >&2; exit 1; }
clock() { date +%s.%N; }
t_all=$(clock)
t_step=$t_all
steps=()
done_step() {  # KEY WHAT: print and record the seconds since the last step
    local now seconds
    now=$(clock)
    seconds=$(awk -v a="$t_step" -v b="$now" 'BEGIN {printf "%.1f", b - a}')
    printf 'setup.sh: %7s s  %s\n' "$seconds" "$2"
    steps+=("$1=$seconds")
    t_step=$now
}

# 1. the carried files: every wheel fetch_wheels.sh writes (optional for the smoke run)
needed=(gsplat mcap mcap_protobuf_support foxglove_schemas_protobuf zstandard lz4 protobuf)
if [ "$smoke" = 0 ]; then
    for name in "${needed[@]}"; do
        compgen -G "$wheels/$name-*.whl" >/dev/null \
            || fail "no $name wheel in $wheels: run bench/gpu/fetch_wheels.sh where pip reaches PyPI and carry bench/gpu/wheels"
    done
fi
command -v "$python" >/dev/null || fail "no $python (set GSC_GPU_PYTHON to the interpreter that has torch)"
"$python" -c "import torch" 2>/dev/null || fail "$python cannot import torch (set GSC_GPU_PYTHON)"
done_step files "files: the wheels, and $python with torch"

# 2. CUDA: a GPU torch sees, the toolkit gsplat compiles with, ninja
if [ "$smoke" = 0 ]; then
    cuda=$("$python" -c "import torch; print(torch.cuda.is_available(), torch.version.cuda)")
    cuda_version=${cuda#* }
    [ "${cuda%% *}" = True ] || fail "no CUDA: torch sees no GPU (torch.cuda.is_available, torch.version.cuda: $cuda)"
    cuda_home=$("$python" -c "from torch.utils.cpp_extension import CUDA_HOME; print(CUDA_HOME or '')")
    [ -n "$cuda_home" ] && [ -x "$cuda_home/bin/nvcc" ] \
        || fail "no CUDA toolkit (nvcc) for gsplat's kernels: set CUDA_HOME (torch found '${cuda_home}')"
    "$python" -c "from torch.utils.cpp_extension import verify_ninja_availability as v; v()" 2>/dev/null \
        || fail "no ninja on PATH: torch builds gsplat's kernels with it"
    done_step cuda "CUDA: torch sees a GPU (CUDA $cuda_version), nvcc in $cuda_home"
fi

# 3. the venv, seeing the interpreter's own packages after its own
if [ ! -x "$vpy" ]; then
    "$python" -m venv --without-pip "$venv" || fail "cannot create a venv with $python -m venv"
    "$python" - "$venv" <<'EOF'
import sys
from pathlib import Path

venv = Path(sys.argv[1])
dirs = [p for p in sys.path if p.endswith(("site-packages", "dist-packages")) and Path(p).is_dir()]
site = next(venv.glob("lib/python*/site-packages"))
# addsitedir (not a bare path) so that the .pth files of those folders are read too
line = f"import site; list(map(site.addsitedir, {dirs!r}))\n"
(site / "_gsc_base_site.pth").write_text(line)
EOF
fi
"$vpy" -c "import torch, pip" 2>/dev/null || fail "the venv $venv does not see torch and pip of $python"
done_step venv "venv $venv"

# 4. the carried wheels this interpreter can install (all of them on the GPU machine)
if compgen -G "$wheels/*.whl" >/dev/null; then
    mapfile -t install < <("$vpy" - "$wheels" <<'EOF'
import sys
from pathlib import Path

try:
    from packaging.tags import sys_tags
    from packaging.utils import parse_wheel_filename
except ImportError:
    from pip._vendor.packaging.tags import sys_tags
    from pip._vendor.packaging.utils import parse_wheel_filename

supported = set(sys_tags())
for wheel in sorted(Path(sys.argv[1]).glob("*.whl")):
    if supported & set(parse_wheel_filename(wheel.name)[3]):
        print(wheel)
    else:
        print(f"setup.sh: {wheel.name} is not for this interpreter: left out", file=sys.stderr)
EOF
)
    if [ "$smoke" = 0 ] && [ "${#install[@]}" -lt "${#needed[@]}" ]; then
        fail "some wheels in $wheels do not fit $python (fetch_wheels.sh GSC_GPU_PYVER)"
    fi
    if [ "${#install[@]}" -gt 0 ]; then
        "$vpy" -m pip install --quiet --no-index --no-deps --no-compile --no-cache-dir \
            --disable-pip-version-check "${install[@]}" || fail "pip could not install the wheels of $wheels"
    fi
    done_step wheels "wheels: ${#install[@]} installed from $wheels"
else
    done_step wheels "wheels: none in $wheels (the smoke run needs none)"
fi

# 5. gscompress itself, editable, without its dependencies (checked below)
if ! "$vpy" -c "import gscompress_cli" 2>/dev/null \
    || [ "$("$vpy" -c 'import gscompress, os; print(os.path.dirname(os.path.dirname(os.path.realpath(gscompress.__file__))))')" != "$root" ]; then
    "$vpy" -m pip install --quiet --no-index --no-deps --no-build-isolation --no-cache-dir \
        --disable-pip-version-check -e "$root" || fail "pip could not install gscompress from $root"
fi
modules=torch,numpy,mcap,mcap_protobuf,foxglove_schemas_protobuf,zstandard,lz4,google.protobuf
modules=$modules,gscompress.pipeline,gscompress_cli.main
[ "$smoke" = 1 ] || modules=$modules,gsplat
missing=$("$vpy" - "$modules" <<'EOF'
import importlib
import sys

for name in sys.argv[1].split(","):
    try:
        importlib.import_module(name)
    except Exception as exc:  # an import error or a broken package: both stop the run
        print(f"{name} ({type(exc).__name__}: {exc})")
EOF
)
[ -z "$missing" ] || fail "the venv cannot import: $(echo "$missing" | tr '\n' ' ')"
done_step gscompress "gscompress (editable) and every module it needs import"

# 6. the variables of later steps; gsplat's kernels built for this GPU's architecture
base_bin=$("$python" -c "import os, sys; print(os.path.dirname(sys.executable))")
cache_dir=${GSCOMPRESS_CACHE_DIR:-$build/kcache}
{
    echo "export GSC_GPU_PY='$vpy'"
    echo "export PATH='$base_bin':\"\$PATH\""
    echo "export TORCH_EXTENSIONS_DIR='$build/torch_extensions'"
    echo "export GSCOMPRESS_CACHE_DIR='$cache_dir'"
    echo "export MAX_JOBS=${MAX_JOBS:-$(nproc)}"
    echo "export PYTHONUNBUFFERED=1"
} >"$build/env.sh"
if [ "$smoke" = 0 ]; then
    arch=${TORCH_CUDA_ARCH_LIST:-$("$vpy" -c 'import torch; print("%d.%d" % torch.cuda.get_device_capability())')}
    echo "export TORCH_CUDA_ARCH_LIST='$arch'" >>"$build/env.sh"
    # shellcheck source=/dev/null
    source "$build/env.sh"
    log=$build/gsplat_build.log
    if ! VERBOSE=1 "$vpy" -c "
from gscompress.render.gsplat_backend import gsplat_kernels
rasterization, why = gsplat_kernels()
raise SystemExit(why if rasterization is None else 0)" >"$log" 2>&1; then
        cp "$log" "$out/gsplat_build.log"
        fail "gsplat's kernels did not build for $arch: $(tail -n 1 "$log") (whole log: OUT/gsplat_build.log)"
    fi
    done_step gsplat_kernels "gsplat's CUDA kernels for compute capability $arch (MAX_JOBS=$MAX_JOBS)"
fi

# 7. what was set up, for the table's JSON
total=$(awk -v a="$t_all" -v b="$(clock)" 'BEGIN {printf "%.1f", b - a}')
"$vpy" - "$out/setup.json" "$smoke" "$total" "${steps[@]}" <<'EOF'
import json
import platform
import sys
from importlib.metadata import PackageNotFoundError, version

import torch

path, smoke, total, *steps = sys.argv[1:]
cuda = torch.cuda.is_available()
try:
    gsplat = version("gsplat")
except PackageNotFoundError:
    gsplat = None
record = {
    "mode": "cpu-smoke" if smoke == "1" else "gpu",
    "python": platform.python_version(),
    "torch": torch.__version__,
    "torch_cuda": torch.version.cuda,
    "gpu": torch.cuda.get_device_name(0) if cuda else None,
    "capability": "%d.%d" % torch.cuda.get_device_capability(0) if cuda else None,
    "gsplat": gsplat,
    "steps_s": {k: float(v) for k, v in (s.rsplit("=", 1) for s in steps)},
    "total_s": float(total),
}
with open(path, "w", encoding="utf-8") as f:
    json.dump(record, f, indent=1)
EOF
echo "setup.sh: ready in $total s (source $build/env.sh; $out/setup.json)"
