#!/usr/bin/env bash
# Regenerates docs/gap-stribeck/: Stribeck friction hidden in the virtual drive, a baseline
# identified without it, and model-gap finding it. Run from the repository root.
set -euo pipefail
out=docs/gap-stribeck
work=$(mktemp -d)
truth="stribeck:breakaway_friction=1.5,velocity=0.05"
rec="recorder --sim --lockstep --no-progress --truth-effect $truth"
mkdir -p "$out"
out=$(cd "$out" && pwd)
cd "$work"
$rec --exciting-trajectory -o noload.mcap
$rec --exciting-trajectory --seed 1 --payload-mass 5 --payload-position 0,0.1 -o load.mcap
$rec --sinusoid --duration 20 --seed 2 -o sinusoid.mcap
identify noload.mcap load.mcap -o baseline.toml
model-gap noload.mcap load.mcap sinusoid.mcap --model baseline.toml --report gap.json \
    --plots plots -o improved.toml
cp baseline.toml gap.json improved.toml plots/*.png "$out/"
cd /
rm -rf "$work"
