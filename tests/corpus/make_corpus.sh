#!/usr/bin/env bash
# Write the compatibility corpus (the logs and shares of tests/corpus/) with the gsc of TREE, and
# expected.json: what that gsc reported of each file, which tests/test_corpus.py holds today's
# gsc to.
#
#   tests/corpus/make_corpus.sh TREE [OUT]
#
# TREE: a gscompress checkout at the commit that writes the corpus, with a .pyshim folder (the
# links that put TREE's gscompress, gscompress_cli and gscompress_schemas on PYTHONPATH):
#   git worktree add /tmp/old e76238d && mkdir /tmp/old/.pyshim && cd /tmp/old/.pyshim \
#     && ln -s ../gscompress . && ln -s ../cli gscompress_cli && ln -s ../schemas gscompress_schemas
# OUT: where the files go (default: this folder). `python` must be an environment with
# gscompress's dependencies; the sequence the files are made from is written to a temporary
# folder and not kept (the test writes it again with `gsc synth`).
set -euo pipefail

tree=$(cd "$1" && pwd)
out=$(cd "${2:-$(dirname "$0")}" && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export PYTHONPATH="$tree/.pyshim" OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
gsc() { python -m gscompress_cli -q --threads 1 "$@"; }
cd "$work"

# The frames: 8 of the synthetic room at 64x48; SLAM works at 32x24 and adds a Gaussian every
# second pixel, so that a map is a few hundred Gaussians and a log a few tens of kB.
gsc synth seq --frames 8 --size 64x48
printf 'densify:\n  stride: 2\n' > small.yaml
printf 'densify:\n  stride: 2\ncheckpoint_every: 2\n' > checkpoints.yaml

gsc slam seq --preset tiny --config small.yaml --size 32x24 -o slam.mcap
gsc prune slam.mcap --keep 0.3 --map-only -o pruned.mcap
gsc share slam.mcap share_compact.mcap --budget 0.2
gsc share slam.mcap share_fp16.mcap --budget 5kB --codec fp16
gsc share slam.mcap share_fp32.mcap --budget 0.1 --codec fp32
# anisotropic (refined: three scales and a rotation), ids, no sums
gsc share slam.mcap share_refined.mcap --budget 0.2 --refine 5 --seq seq --ids --no-sums
gsc share slam.mcap share_keyframes.mcap --budget 0.2 --keyframes 1 --seq seq
gsc merge slam.mcap share_keyframes.mcap --seq seq --iters 5 --codec compact -o merged.mcap
gsc export-ply pruned.mcap -o pruned.ply
gsc import-ply pruned.ply -o imported.mcap
# A run stopped after 3 of its 8 frames (as Ctrl-C stops it), compact, a checkpoint every 2
# frames: what `gsc slam --resume` continues.
python - <<'EOF'
from gscompress.pipeline import slam_file


def stop_after_three(done, total, stats):
    if done == 3:
        raise KeyboardInterrupt


try:
    slam_file("seq", "interrupted.mcap", preset="tiny", config_path="checkpoints.yaml",
              size=(32, 24), codec="compact", progress=stop_after_three)
except KeyboardInterrupt:
    pass
else:
    raise SystemExit("the run was not interrupted")
EOF

files=(slam pruned share_compact share_fp16 share_fp32 share_refined share_keyframes merged
       imported interrupted)
for name in "${files[@]}"; do
    gsc info --json "$name.mcap" > "$name.info.json"
    if gsc export-traj "$name.mcap" -o "$name.traj.txt" 2> /dev/null; then :; fi
done
for name in slam merged interrupted; do
    gsc eval "$name.mcap" --seq seq --no-lpips --json > "$name.eval.json"
done
printf '0 0 0 0 0 0 1\n' > identity.txt
gsc align slam.mcap merged.mcap -o align_slam_merged.txt
gsc align share_refined.mcap slam.mcap --init identity.txt -o align_share_refined_slam.txt

commit=$(git -C "$tree" rev-parse HEAD)
python - "$commit" "${files[@]}" <<'EOF'
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

commit, names = sys.argv[1], sys.argv[2:]
files = {}
for name in names:
    info = json.loads(Path(f"{name}.info.json").read_text())
    info.pop("path")  # where it was read from
    for histogram in ("importance_histogram", "importance_histogram_log"):
        info["map"].pop(histogram)  # the quantiles say as much in less
    traj = Path(f"{name}.traj.txt")
    files[f"{name}.mcap"] = {
        "info": info,
        "trajectory": traj.read_text() if traj.exists() else None,
    }
    evaluation = Path(f"{name}.eval.json")
    if evaluation.exists():
        scores = json.loads(evaluation.read_text())
        keys = ("ate_rmse_cm", "ate_splatam_cm", "psnr", "ssim", "depth_l1_cm",
                "frames_evaluated", "frames_carried_left_out", "gaussians")
        files[f"{name}.mcap"]["eval"] = {key: scores[key] for key in keys}
align = [
    {"source": f"{source}.mcap", "target": f"{target}.mcap", "init_identity": init,
     "T_target_source": np.loadtxt(f"align_{source}_{target}.txt").tolist()}
    for source, target, init in (("slam", "merged", False), ("share_refined", "slam", True))
]
sequence = {
    str(p.relative_to("seq")): hashlib.sha256(p.read_bytes()).hexdigest()
    for p in sorted(Path("seq").rglob("*"))
    if p.is_file()
}
expected = {
    "commit": commit,
    "sequence": {"synth": ["--frames", "8", "--size", "64x48"], "sha256": sequence},
    "files": files,
    "align": align,
}
Path("expected.json").write_text(json.dumps(expected, indent=1, sort_keys=True) + "\n")
EOF

for name in "${files[@]}"; do
    cp "$name.mcap" "$out/"
done
cp expected.json "$out/"
du -cb "$out"/*.mcap "$out/expected.json" | tail -1
