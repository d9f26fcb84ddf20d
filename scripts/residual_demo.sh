#!/usr/bin/env bash
# The residual loop end to end (docs/residual.md), one command:
#
#   scripts/residual_demo.sh [OUT] [--docs]        (default OUT: runs/residual_demo/<time>)
#
# 1. the node graph on the plant with effects nobody declared (--effect), shipped model, bag:
#    a slipping axis (OUT/axis/), and a slipping axis with a vacuum leak (OUT/axis_leak/);
# 2. peel residual on that bag: the residual, the effects it names, the corrected model;
# 3. the graph again, same seed and effects, planner and learner starting from the corrected model;
# 4. planner cost J per task and safety margin, before and after (peel_experiments.residual_compare);
# 5. the plant's own documented differences, with the shipped simulator-trained model: the graph
#    on the plant (default level 3, and level 1) without injected effects and peel residual on
#    its bag; the same analysis on plant data under exploratory commands (levels 3 and 1);
# 6. the scenario table: known undeclared effects, three seeds (scripts/residual_scenarios.py);
# 7. steps 1-4 for two effects drawn as the power study draws them, acting on the plant
#    (peel_experiments.drawn_effects, seed S+1101), each analysed with the defaults and again with
#    the output-error fit (residual.open_loop_fit) in OUT/drawn_<i>/.
# With --docs the reports and figures are copied to docs/residual/ (what the docs page shows).
# Environment: PEEL_DEMO_TASKS (default 30), PEEL_DEMO_SEED (default 300: graph seeds S, S+1,
# S+2; scenario seeds S+101..S+103; exploratory plant seeds S+201..S+203), ROS_DOMAIN_ID.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
out="" ; docs=0
for arg in "$@"; do
  case "$arg" in
    --docs) docs=1 ;;
    -h|--help) sed -n 2,18p "$0"; exit 0 ;;
    -*) echo "residual_demo: error: unknown option $arg" >&2; exit 2 ;;
    *) out="$arg" ;;
  esac
done
out="${out:-runs/residual_demo/$(date +%Y%m%d-%H%M%S)}"
if [ -e "$out" ]; then
  echo "residual_demo: error: $out already exists (give a new directory)" >&2
  exit 2
fi
tasks="${PEEL_DEMO_TASKS:-30}"
seed="${PEEL_DEMO_SEED:-300}"
[ -x .venv/bin/peel ] || bash scripts/setup.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export TORCH_EXTENSIONS_DIR="${TORCH_EXTENSIONS_DIR:-$root/.venv/torch_extensions}"
peel=.venv/bin/peel
py=.venv/bin/python
mkdir -p "$out"
absout="$(cd "$out" && pwd)"
cat > "$out/level1.yaml" <<YAML
peel_sim_node:
  ros__parameters:
    plant:
      level: 1
YAML

# Steps 1-4 for one set of undeclared effects (MODULE:FUNCTION each), in $out/<name>/.
story() {
  local name="$1"; shift
  local d="$out/$name"
  mkdir -p "$d"
  local effects=()
  for e in "$@"; do effects+=(--effect "$e"); done
  set -x
  # 1. the plant with undeclared effects, the shipped model
  $peel graph --plant plant --tasks "$tasks" --seed "$seed" "${effects[@]}" \
    --record "$d/before/bag" --out "$d/before/run"
  { set +x; } 2>/dev/null
  correct "$d" "$d" "corrected model" "$@"
}

# Steps 2-4 on the bag of $1/before into $2 (residual/, after/, comparison/); $3 the label,
# then the effects; PEEL_DEMO_RESIDUAL_PARAMS, if set, is the parameter file of step 2.
correct() {
  local d="$1" o="$2" label="$3"; shift 3
  local effects=() rparams=()
  for e in "$@"; do effects+=(--effect "$e"); done
  [ -z "${PEEL_DEMO_RESIDUAL_PARAMS:-}" ] || rparams=(--params "$PEEL_DEMO_RESIDUAL_PARAMS")
  mkdir -p "$o"
  set -x
  # 2. trace the residual
  $peel residual "$d/before/bag" "${rparams[@]}" --out "$o/residual" --no-progress
  { set +x; } 2>/dev/null
  if [ ! -f "$o/residual/corrected.safetensors" ]; then
    echo "residual_demo: $o: no effect named, so no corrected model to run again" >&2
    return 0
  fi
  local model
  model="$(cd "$o/residual" && pwd)/corrected.safetensors"
  cat > "$o/after.yaml" <<YAML
peel_planner_node:
  ros__parameters:
    model:
      path: $model
model_learner_node:
  ros__parameters:
    node:
      init_model: $model
YAML
  set -x
  # 3. the same tasks with the corrected model
  $peel graph --plant plant --tasks "$tasks" --seed "$seed" "${effects[@]}" \
    --params "$o/after.yaml" --record "$o/after/bag" --out "$o/after/run"
  # 4. planner cost and safety margin, before and after
  $py -m peel_experiments.residual_compare --before "$d/before/run" "$d/before/bag" \
    --after "$o/after/run" "$o/after/bag" --out "$o/comparison" \
    --label-before "shipped model" --label-after "$label"
  { set +x; } 2>/dev/null
}

ex=peel_sim_node.example_effects
story axis "$ex:slipping_axis"
story axis_leak "$ex:slipping_axis" "$ex:vacuum_leak"
set -x
# 5. the plant's own differences, with the shipped simulator-trained model (levels 3 and 1)
$peel graph --plant plant --tasks "$tasks" --seed "$((seed + 1))" \
  --record "$out/plant/bag" --out "$out/plant/run"
$peel residual "$out/plant/bag" --out "$out/plant_residual" --no-progress
$peel graph --plant plant --tasks "$tasks" --seed "$((seed + 2))" --params "$out/level1.yaml" \
  --record "$out/plant_l1/bag" --out "$out/plant_l1/run"
$peel residual "$out/plant_l1/bag" --out "$out/plant_l1_residual" --no-progress
$py scripts/residual_scenarios.py --scenarios plant \
  --seeds "$((seed + 201)),$((seed + 202)),$((seed + 203))" --out "$out/plant_exploratory.jsonl"
$py scripts/residual_scenarios.py --scenarios plant --level 1 \
  --seeds "$((seed + 201)),$((seed + 202)),$((seed + 203))" --out "$out/plant_l1_exploratory.jsonl"
# 6. the scenario table (default plant level)
$py scripts/residual_scenarios.py --seeds "$((seed + 101)),$((seed + 102)),$((seed + 103))" \
  --out "$out/scenarios.jsonl"
# 7. two effects drawn as the power study draws them, defaults and the output-error fit
$py -m peel_experiments.drawn_effects --seed "$((seed + 1101))" --count 2 --out "$out/drawn"
set +x
export PYTHONPATH="$absout/drawn${PYTHONPATH:+:$PYTHONPATH}"
cat > "$out/open_loop_fit.yaml" <<YAML
peel_residual:
  ros__parameters:
    residual:
      open_loop_fit: true
YAML
for i in 0 1; do
  story "drawn_$i" "drawn_effect_$i:effect"
  PEEL_DEMO_RESIDUAL_PARAMS="$absout/open_loop_fit.yaml" \
    correct "$out/drawn_$i" "$out/drawn_$i/oe" "corrected model (output-error fit)" "drawn_effect_$i:effect"
done
if [ "$docs" = 1 ]; then
  dst=docs/residual
  rm -rf "$dst"/demo_* "$dst/plant" "$dst/plant_l1"
  cp "$out/drawn/draws.json" "$dst/drawn_effects.json"
  for name in axis axis_leak drawn_0 drawn_0/oe drawn_1 drawn_1/oe; do
    mkdir -p "$dst/demo_$name"
    cp "$out/$name"/residual/report.{md,json} "$out/$name"/residual/*.png "$dst/demo_$name/"
    if [ -d "$out/$name/comparison" ]; then
      cp "$out/$name"/comparison/comparison.{md,json,png} "$dst/demo_$name/"
    fi
  done
  mkdir -p "$dst/plant" "$dst/plant_l1"
  cp "$out"/plant_residual/report.{md,json} "$out"/plant_residual/*.png "$dst/plant/"
  cp "$out"/plant_l1_residual/report.{md,json} "$out"/plant_l1_residual/*.png "$dst/plant_l1/"
  cp "$out/plant_exploratory.jsonl" "$dst/plant/"
  cp "$out/plant_l1_exploratory.jsonl" "$dst/plant_l1/"
  cp "$out/scenarios.jsonl" "$dst/"
  echo "residual_demo: copied the reports and figures to $dst/"
fi
echo "residual_demo: done; everything is in $out"
