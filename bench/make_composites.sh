#!/usr/bin/env bash
# The composites of bench/real.py: rendered objects in the shared real footage (jsr synth
# --background), 100-120 frames each, 640x480. The *_s1_jump ones are the tuning set; the
# other six are held out (report on them, do not tune on them).
#   bash bench/make_composites.sh OUT_DIR      # about 15 minutes on 2 cores
#   bash bench/make_composites.sh OUT_DIR 10   # another set: every seed + 10 (other objects, motions)
#   python bench/real.py --composites OUT_DIR/redkitchen_s2_smooth,...
set -euo pipefail
out="${1:?usage: bash bench/make_composites.sh OUT_DIR [SEED_OFFSET]}"
offset="${2:-0}"
cd "$(dirname "$0")/.."
rk=../shared/data/redkitchen300
bn=../shared/data/bonn_crowd200
synth() { python3 -m jsr.cli synth "$out/$1" --overwrite -q "${@:2}"; }
seed() { echo $(( $1 + offset )); }
synth redkitchen_s1_jump     --background $rk --start 0   --frames 120 --seed $(seed 1) --motion jump   --objects 1
synth redkitchen_s2_smooth   --background $rk --start 200 --frames 100 --seed $(seed 2) --motion smooth --objects 1
synth redkitchen_s3_two_jump --background $rk --start 60  --frames 120 --seed $(seed 3) --motion jump   --objects 2
synth redkitchen_s4_two_sim  --background $rk --start 0   --frames 120 --seed $(seed 4) --motion jump   --objects 2 --simultaneous
# bonn_crowd200's ground truth is off at its start: its first two samples turn 1.0 degrees
# where the images say 0.4, and the first colour frame precedes the first sample (its pose is
# extrapolated): an object composited from frame 0 sat 3-6 cm from where frames 2-9 show it.
# The Bonn composites start at frame 2 or later.
synth bonn_s1_jump           --background $bn --start 2   --frames 120 --seed $(seed 1) --motion jump   --objects 1
synth bonn_s2_smooth         --background $bn --start 40  --frames 120 --seed $(seed 2) --motion smooth --objects 1
synth bonn_s3_two_jump       --background $bn --start 80  --frames 120 --seed $(seed 3) --motion jump   --objects 2
synth bonn_s4_two_sim        --background $bn --start 2   --frames 120 --seed $(seed 4) --motion jump   --objects 2 --simultaneous
