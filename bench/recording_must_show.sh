#!/usr/bin/env bash
# The figures of docs/recordings.md, "The same map from a folder and from a recording": tabletop
# (depth_scale 1000, carried as 16UC1 millimetres) as a ROS 2 MCAP bag, a ROS 2 sqlite bag and
# a ROS 1 bag, `gsc slam` on the folder and on each (frames 0:20, cpu preset, one thread), the
# logs compared once decoded (bench/recording_equality.py); the same with JPEG colour and
# compressedDepth (ATE and PSNR against the folder's run); and `gsc eval` of the ROS 2 bag's run
# with /tf ground truth against the folder's groundtruth.txt. One command at a time.
#
#   bash bench/recording_must_show.sh [DATA_FOLDER] [OUT]
set -euo pipefail
D=${1:-../shared/data/tsdffusion_tabletop_box}
OUT=${2:-bench_recording_must_show}
GT=(--gt-frames world camera_color_optical_frame)
mkdir -p "$OUT"
run() { echo "+ $*" >&2; nice -n 10 "$@"; }

for fmt in ros2 ros2-sqlite ros1; do
  name=tt_${fmt/-/_}; [ "$fmt" = ros1 ] && name=$name.bag
  [ -e "$OUT/$name" ] || run gsc convert "$D" -o "$OUT/$name" --format "$fmt" --depth-encoding 16UC1
done
[ -e "$OUT/tt_jpeg" ] || run gsc convert "$D" -o "$OUT/tt_jpeg" --format ros2 \
  --color-encoding jpeg --depth-encoding compressedDepth

slam() { run gsc --threads 1 slam "$@" --frames 0:20 --preset cpu --force; }
# (a) the folder and each bag; the bags' ground truth is the folder's groundtruth.txt
slam "$D" -o "$OUT/folder.mcap"
for bag in tt_ros2 tt_ros2_sqlite tt_ros1.bag; do
  slam "$OUT/$bag" -o "$OUT/${bag%.bag}.mcap" --gt "$D/groundtruth.txt"
done
run python bench/recording_equality.py "$OUT/folder.mcap" "$OUT/tt_ros2.mcap" \
  "$OUT/tt_ros2_sqlite.mcap" "$OUT/tt_ros1.mcap" --json "$OUT/equality.json" || true

# (b) JPEG colour and compressedDepth: ATE and PSNR against the folder's frames
slam "$OUT/tt_jpeg" -o "$OUT/tt_jpeg.mcap" --gt "$D/groundtruth.txt"
for log in folder tt_jpeg; do
  run gsc eval "$OUT/$log.mcap" --seq "$D" --no-lpips --json > "$OUT/eval_$log.json"
done

# (c) a run on the ROS 2 bag with /tf ground truth, evaluated with it and with groundtruth.txt
slam "$OUT/tt_ros2" -o "$OUT/tt_ros2_tf.mcap" "${GT[@]}"
run gsc eval "$OUT/tt_ros2_tf.mcap" --seq "$OUT/tt_ros2" --no-lpips --json > "$OUT/eval_tf.json"
run gsc eval "$OUT/tt_ros2_tf.mcap" --seq "$OUT/tt_ros2" --gt "$D/groundtruth.txt" --no-lpips \
  --json > "$OUT/eval_tf_file.json"
run gsc eval "$OUT/tt_ros2_tf.mcap" --seq "$D" --no-lpips --json > "$OUT/eval_tf_folder.json"

python - "$OUT" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
for name in ("folder", "tt_jpeg", "tf", "tf_file", "tf_folder"):
    r = json.loads((out / f"eval_{name}.json").read_text())
    print(f"{name}: ATE {r['ate_rmse_cm']!r} cm ({r['ate_frames']} frames, ground truth from the "
          f"{r['ground_truth']}), PSNR {r['psnr']!r} dB, SSIM {r['ssim']!r}, depth L1 "
          f"{r.get('depth_l1_cm')!r} cm, {r['frames_evaluated']} frames")
EOF
