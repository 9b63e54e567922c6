#!/usr/bin/env bash
# Fills bench/gpu/wheels/ (git-ignored) with the wheels that bench/gpu/setup.sh installs on a GPU
# machine without network access. Run it where pip reaches PyPI, in the checkout whose tree the
# GPU machine receives, then carry bench/gpu/wheels with that tree (docs/performance.md#gpu).
#
#   bash bench/gpu/fetch_wheels.sh
#
# What travels: gsplat (a pure-Python wheel: no prebuilt gsplat matches a CUDA 13 torch, so its
# kernels are compiled there on first use, against the torch found there) and the dependencies
# of gscompress that the GPU image lacks (mcap and its protobuf support, the Foxglove schemas,
# zstandard, lz4, protobuf), each at the version installed here, for CPython GSC_GPU_PYVER
# (default 3.12, the GPU image's) on x86-64 Linux. torch, numpy, scipy, pillow, click, PyYAML,
# matplotlib and gsplat's own needs (ninja, jaxtyping, rich) are already there. About 14 MB.
#
# Environment: GSC_GPU_PYVER (3.12), GSPLAT_VERSION (1.5.3, the version docs/performance.md's
# GPU figures were measured with), GSC_GPU_WHEELS (the folder; bench/gpu/wheels).
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
wheels=${GSC_GPU_WHEELS:-$root/bench/gpu/wheels}
pyver=${GSC_GPU_PYVER:-3.12}
gsplat_version=${GSPLAT_VERSION:-1.5.3}
python=${PYTHON:-python3}

# gscompress's own dependencies that the GPU image does not hold, pinned to this environment's
# versions (the ones the tests passed with here)
deps=(mcap mcap-protobuf-support foxglove-schemas-protobuf zstandard lz4 protobuf)
pins=$("$python" - "${deps[@]}" <<'EOF'
import sys
from importlib.metadata import PackageNotFoundError, version

pins = []
for name in sys.argv[1:]:
    try:
        pins.append(f"{name}=={version(name)}")
    except PackageNotFoundError:
        sys.exit(f"fetch_wheels.sh: {name} is not installed here (pip install -e . first)")
print(" ".join(pins))
EOF
)

mkdir -p "$wheels"
rm -f "$wheels"/*.whl  # one version of each: two would stop the install there
platforms=()
for tag in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
    manylinux1_x86_64; do
    platforms+=(--platform "$tag")
done
# shellcheck disable=SC2086  # $pins is a list of NAME==VERSION words
"$python" -m pip download --quiet --no-deps --only-binary=:all: --python-version "$pyver" \
    --implementation cp "${platforms[@]}" -d "$wheels" "gsplat==$gsplat_version" $pins
ls -1 "$wheels"
echo "fetch_wheels.sh: $(find "$wheels" -name '*.whl' | wc -l) wheels, $(du -sh "$wheels" | cut -f1) in $wheels"
