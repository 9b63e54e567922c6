#!/usr/bin/env bash
# One call of a GPU machine for the sequences after tabletop (bench/gpu/table.sh's): the same
# setup and table, without the GPU tests.
#
#   bash bench/gpu/sequences.sh frag1      # 3dmatch_office_frag1, 50 frames: unpruned, then PWAS
#   bash bench/gpu/sequences.sh icl        # icl_livingroom1_clean_o3d211 frames 0:120: both
#                                          # runs at once, sharing the GPU (one after the other
#                                          # would not end within 8 minutes)
#   bash bench/gpu/sequences.sh icl --cpu-smoke
#
# Stage the sequence first (bench/gpu/stage_data.sh frag1 | icl) and carry bench/gpu/wheels and
# bench/gpu/data. Further options go to table.sh (e.g. -- --runs pwas).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
case ${1:-} in
    frag1) shift; exec bash "$here/table.sh" --seq frag1 --no-tests "$@" ;;
    icl) shift; exec bash "$here/table.sh" --seq icl --no-tests --parallel "$@" ;;
    *) echo "usage: sequences.sh frag1|icl [table.sh options]" >&2; exit 2 ;;
esac
