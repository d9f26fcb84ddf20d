#!/usr/bin/env bash
# The residual loop end to end (docs/residual.md), one command:
#
#   scripts/residual_demo.sh [OUT] [--docs]        (default OUT: runs/residual_demo/<time>)
#
# 1. the node graph on the plant with two effects nobody declared (--effect), shipped model, bag;
# 2. peel residual on that bag: the residual, the effects it names, the corrected model;
# 3. the graph again, same seed and effects, planner and learner starting from the corrected model;
# 4. planner cost J per task and safety margin, before and after (peel_bringup.residual_compare);
# 5. the plant's own documented differences: the graph on the plant without injected effects and
#    peel residual with the shipped simulator-trained model; and the same analysis on plant data
#    under exploratory commands;
# 6. the scenario table: known undeclared effects, three seeds (scripts/residual_scenarios.py).
# With --docs the reports and figures are copied to docs/residual/ (what the docs page shows).
# Environment: PEEL_DEMO_TASKS (default 30), PEEL_DEMO_SEED (default 0), ROS_DOMAIN_ID.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
out="" ; docs=0
for arg in "$@"; do
  case "$arg" in
    --docs) docs=1 ;;
    -h|--help) sed -n 2,16p "$0"; exit 0 ;;
    *) out="$arg" ;;
  esac
done
out="${out:-runs/residual_demo/$(date +%Y%m%d-%H%M%S)}"
if [ -e "$out" ]; then
  echo "residual_demo: error: $out already exists (give a new directory)" >&2
  exit 2
fi
tasks="${PEEL_DEMO_TASKS:-30}"
seed="${PEEL_DEMO_SEED:-0}"
[ -x .venv/bin/peel ] || bash scripts/setup.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export TORCH_EXTENSIONS_DIR="${TORCH_EXTENSIONS_DIR:-$root/.venv/torch_extensions}"
peel=.venv/bin/peel
py=.venv/bin/python
effects=(--effect peel_sim_node.example_effects:slipping_axis
         --effect peel_sim_node.example_effects:vacuum_leak)
mkdir -p "$out"
absout="$(cd "$out" && pwd)"
set -x
# 1. the plant with undeclared effects, the shipped model
$peel graph --plant plant --tasks "$tasks" --seed "$seed" "${effects[@]}" \
  --record "$out/before/bag" --out "$out/before/run"
# 2. trace the residual
$peel residual "$out/before/bag" --out "$out/residual" --no-progress
set +x
if [ -f "$out/residual/corrected.safetensors" ]; then
  cat > "$out/after.yaml" <<EOF
peel_planner_node:
  ros__parameters:
    model:
      path: $absout/residual/corrected.safetensors
model_learner_node:
  ros__parameters:
    node:
      init_model: $absout/residual/corrected.safetensors
EOF
  set -x
  # 3. the same tasks with the corrected model
  $peel graph --plant plant --tasks "$tasks" --seed "$seed" "${effects[@]}" \
    --params "$out/after.yaml" --record "$out/after/bag" --out "$out/after/run"
  # 4. planner cost and safety margin, before and after
  $py -m peel_bringup.residual_compare --before "$out/before/run" "$out/before/bag" \
    --after "$out/after/run" "$out/after/bag" --out "$out/comparison" \
    --label-before "shipped model" --label-after "corrected model"
  set +x
else
  echo "residual_demo: no effect named, so no corrected model to run again" >&2
fi
set -x
# 5. the plant's own differences, with the shipped simulator-trained model
$peel graph --plant plant --tasks "$tasks" --seed "$((seed + 1))" \
  --record "$out/plant/bag" --out "$out/plant/run"
$peel residual "$out/plant/bag" --out "$out/plant_residual" --no-progress
$py scripts/residual_scenarios.py --scenarios plant --seeds "$((seed + 201)),$((seed + 202)),$((seed + 203))" \
  --out "$out/plant_exploratory.jsonl"
# 6. the scenario table
$py scripts/residual_scenarios.py --seeds "$((seed + 101)),$((seed + 102)),$((seed + 103))" \
  --out "$out/scenarios.jsonl"
set +x
if [ "$docs" = 1 ]; then
  dst=docs/residual
  rm -rf "$dst/demo" "$dst/plant"
  mkdir -p "$dst/demo" "$dst/plant"
  cp "$out"/residual/report.{md,json} "$out"/residual/*.png "$dst/demo/"
  [ -d "$out/comparison" ] && cp "$out"/comparison/comparison.{md,json,png} "$dst/demo/"
  cp "$out"/plant_residual/report.{md,json} "$out"/plant_residual/*.png "$dst/plant/"
  cp "$out/plant_exploratory.jsonl" "$dst/plant/"
  cp "$out/scenarios.jsonl" "$dst/"
  echo "residual_demo: copied the reports and figures to $dst/"
fi
echo "residual_demo: done; everything is in $out"
