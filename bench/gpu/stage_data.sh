#!/usr/bin/env bash
# Copies sequences into bench/gpu/data/ (git-ignored), so that they travel with the working tree
# to a GPU machine that receives the checkout alone (the data folder beside the checkout,
# ../shared/data, does not go with it). Prints what the tree then weighs with the carried folders.
#
#   bash bench/gpu/stage_data.sh tabletop            # before bench/gpu/table.sh
#   bash bench/gpu/stage_data.sh frag1               # before bench/gpu/sequences.sh frag1
#   bash bench/gpu/stage_data.sh icl                 # before bench/gpu/sequences.sh icl
#
# One sequence a call is the plan: each is about 24 MB, and the tree, the wheels (about 14 MB) and
# the data must stay within 64 MiB together. Sequences staged before are removed first.
# Environment: GSC_DATA (where the sequences are; default ../shared/data beside the checkout).
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
source_dir=${GSC_DATA:-$root/../shared/data}
staged=$root/bench/gpu/data
[ $# -ge 1 ] || { echo "usage: stage_data.sh NAME ... (a short name of bench/gpu/sequences.txt or a folder name)" >&2; exit 2; }

folders=()
for name in "$@"; do
    folder=$(awk -v n="$name" '$1 == n {print $2}' "$root/bench/gpu/sequences.txt")
    folder=${folder:-$name}
    [ -d "$source_dir/$folder" ] || { echo "stage_data.sh: no sequence $source_dir/$folder (set GSC_DATA)" >&2; exit 1; }
    folders+=("$source_dir/$folder")
done
rm -rf "$staged"
mkdir -p "$staged"
cp -r "${folders[@]}" "$staged/"
# the commit the data goes with, for a tree that travels without its git folder (table.py)
dirty=$(git -C "$root" status --porcelain --untracked-files=no | head -c 1)
echo "$(git -C "$root" rev-parse HEAD) ${dirty:+dirty}" >"$staged/commit.txt"

tree_kib=$(git -C "$root" ls-files -z --cached --others --exclude-standard \
    | (cd "$root" && xargs -0 du -ck 2>/dev/null) | tail -1 | cut -f1)
data_kib=$(du -sk "$staged" | cut -f1)
wheels_kib=$(du -sk "$root/bench/gpu/wheels" 2>/dev/null | cut -f1 || echo 0)
total_mib=$(( (tree_kib + data_kib + ${wheels_kib:-0}) / 1024 ))
echo "stage_data.sh: staged ${*} at $(cut -c1-12 "$staged/commit.txt")"
echo "stage_data.sh: tree ${tree_kib} KiB + data ${data_kib} KiB + wheels ${wheels_kib:-0} KiB = ${total_mib} MiB (limit 64 MiB)"
echo "stage_data.sh: carry bench/gpu/wheels and bench/gpu/data"
[ "$total_mib" -lt 64 ] || { echo "stage_data.sh: over 64 MiB: stage fewer sequences" >&2; exit 1; }
