#!/usr/bin/env bash
# Mutation testing of GARO's stages and strategy with mutmut: activity, normals, curvature, knn, select
# (the joint selection) and garo_strategy (GaroStrategy's own logic, its compaction rounds and its
# settings), and compaction's own modules (schedule, decision, guard, importance, report; training.py, the
# nerfstudio glue, is exercised by slow training tests only and is left out). Each mutant is run against the fast unit tests only (tests/test_redundancy_*.py,
# tests/test_garo_strategy.py, and the tests of test_compaction.py and test_model_settings.py not marked
# slow: seconds, no training through nerfstudio).
#
#   bash scripts/mutation.sh                                  # both halves, about 1.5 hours on 2 CPU cores
#   MUTATION_NAMES="garo_ns.redundancy.activity.* garo_ns.redundancy.normals.* garo_ns.redundancy.curvature.* garo_ns.redundancy.select.* garo_ns.garo_strategy.*" \
#     bash scripts/mutation.sh                                # the first half only (about an hour)
#   MUTATION_NAMES="garo_ns.redundancy.knn.*" bash scripts/mutation.sh   # the kNN half only (17 to 25 minutes)
#   MUTATION_NAMES="garo_ns.compaction.*" bash scripts/mutation.sh        # compaction's modules only
#   MUTATION_JOBS=8 bash scripts/mutation.sh
#
# Works in a scratch copy (build/mutation/, git-ignored) so the checkout is never mutated, then
# writes one results file per module it ran, benchmarks/results/mutation_<module>.json (see
# scripts/mutation_report.py collect), and rebuilds benchmarks/results/mutation_report.md from
# all five: the score and every surviving mutant with its diff and the reason it is equivalent or
# harmless (from scripts/mutation_notes.json; a survivor without a note is listed as UNEXPLAINED
# and makes the script exit 1). MUTATION_NOTE, if set, is recorded with the run.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
MUTMUT_VERSION=3.8.1
if ! .venv/bin/python -c "import mutmut, sys; sys.exit(mutmut.__version__ != '$MUTMUT_VERSION')" 2> /dev/null; then
  .venv/bin/python -m pip install -q "mutmut==$MUTMUT_VERSION"
fi
work=${MUTATION_DIR:-build/mutation}
rm -rf "$work"
mkdir -p "$work/tests"
cp -r garo_ns "$work/"
find "$work/garo_ns" -name __pycache__ -prune -exec rm -rf {} +
cp pyproject.toml "$work/"  # pytest's settings; it has no [tool.mutmut], so setup.cfg below is read
tests=(tests/test_redundancy_stages.py tests/test_redundancy_strategy.py tests/test_garo_strategy.py
  tests/test_compaction.py tests/test_model_settings.py)
cp tests/conftest.py "${tests[@]}" "$work/tests/"
cp -r tests/data "$work/tests/"  # the settings snapshot and the old config.yml
cat > "$work/setup.cfg" << EOF
[mutmut]
source_paths = garo_ns
only_mutate =
    garo_ns/redundancy/activity.py
    garo_ns/redundancy/normals.py
    garo_ns/redundancy/curvature.py
    garo_ns/redundancy/knn.py
    garo_ns/redundancy/select.py
    garo_ns/garo_strategy.py
    garo_ns/compaction/schedule.py
    garo_ns/compaction/decision.py
    garo_ns/compaction/guard.py
    garo_ns/compaction/importance.py
    garo_ns/compaction/report.py
pytest_add_cli_args_test_selection =
$(printf '    %s\n' "${tests[@]}")
pytest_add_cli_args =
    -p
    no:cacheprovider
    --hypothesis-seed=0
    -m
    not slow
process_isolation = forkserver
EOF
cd "$work"
export TORCHDYNAMO_DISABLE=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
export GARO_PROPERTY_EXAMPLES=${GARO_PROPERTY_EXAMPLES:-25}
# Three passes (the stages and the strategy, kNN, then compaction): the first one's results are there sooner.
# MUTATION_NAMES (mutmut name globs, e.g. "garo_ns.redundancy.curvature.*") runs those mutants only.
passes=("garo_ns.redundancy.activity.* garo_ns.redundancy.normals.* garo_ns.redundancy.curvature.* garo_ns.redundancy.select.* garo_ns.garo_strategy.*" "garo_ns.redundancy.knn.*" "garo_ns.compaction.*")
if [ -n "${MUTATION_NAMES:-}" ]; then passes=("$MUTATION_NAMES"); fi
start=$SECONDS
for names in "${passes[@]}"; do
  # shellcheck disable=SC2086
  "$root/.venv/bin/mutmut" run --max-children "${MUTATION_JOBS:-2}" $names >> mutmut-run.log 2>&1 || {
    tail -c 3000 mutmut-run.log
    exit 1
  }
done
"$root/.venv/bin/mutmut" export-cicd-stats > /dev/null
"$root/.venv/bin/mutmut" results --all true > results.txt
export MUTATION_WALL_S=$((SECONDS - start)) MUTATION_JOBS=${MUTATION_JOBS:-2}
cd "$root"
.venv/bin/python scripts/mutation_report.py collect "$work" benchmarks/results
.venv/bin/python scripts/mutation_report.py report benchmarks/results scripts/mutation_notes.json \
  benchmarks/results/mutation_report.md
