#!/usr/bin/env bash
# Regenerates docs/gap-combined/: two effects hidden together in the virtual drive (Stribeck
# friction and a position ripple), a baseline identified without them (its fit figures
# included), and model-gap finding both. Run from the repository root.
set -euo pipefail
out=docs/gap-combined
work=$(mktemp -d)
truth=(--truth-effect "stribeck:breakaway_friction=1.5,velocity=0.05"
       --truth-effect "position_ripple:amplitude=0.5,spatial_frequency=6,phase=0.3")
rec=(recorder --sim --lockstep --no-progress "${truth[@]}")
mkdir -p "$out"
out=$(cd "$out" && pwd)
cd "$work"
"${rec[@]}" --exciting-trajectory -o noload.mcap
"${rec[@]}" --exciting-trajectory --seed 1 --payload-mass 5 --payload-position 0,0.1 -o load.mcap
"${rec[@]}" --sinusoid --duration 20 --seed 2 -o sinusoid.mcap
identify noload.mcap load.mcap -o baseline.toml --plots plots
model-gap noload.mcap load.mcap sinusoid.mcap --model baseline.toml --report gap.json \
    --plots plots -o improved.toml
rm -f "$out"/*.png "$out"/*.toml "$out"/gap.json
cp baseline.toml gap.json improved.toml plots/*.png "$out/"
cd /
rm -rf "$work"
