#!/usr/bin/env bash
# Regenerates docs/gap-stribeck/: Stribeck friction hidden in the virtual drive, a baseline
# identified without it, and model-gap finding it. Run from the repository root.
set -euo pipefail
out=docs/gap-stribeck
work=$(mktemp -d)
truth="stribeck:breakaway_friction=1.5,velocity=0.05"
rec="recorder --sim --lockstep --no-progress --truth-effect $truth"
$rec --exciting-trajectory -o "$work/noload.mcap"
$rec --exciting-trajectory --seed 1 --payload-mass 5 --payload-position 0,0.1 -o "$work/load.mcap"
$rec --sinusoid --duration 20 --seed 2 -o "$work/sinusoid.mcap"
identify "$work/noload.mcap" "$work/load.mcap" -o "$work/baseline.toml"
mkdir -p "$out"
cp "$work/baseline.toml" "$out/baseline.toml"
cd "$work"
model-gap noload.mcap load.mcap sinusoid.mcap --model baseline.toml --report gap.json \
    --plots plots -o improved.toml
cd - > /dev/null
cp "$work/gap.json" "$work/improved.toml" "$out/"
cp "$work"/plots/*.png "$out/"
rm -rf "$work"
