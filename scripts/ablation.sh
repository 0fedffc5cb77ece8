#!/usr/bin/env bash
# The ablation pipeline (ablation/dvc.yaml), its points ABLATION_JOBS at a time (default 2).
#
#   scripts/ablation.sh                  # both recipes: data, 16 points two at a time, 2 reports
#   scripts/ablation.sh paper            # one recipe
#   ABLATION_JOBS=4 scripts/ablation.sh  # four at a time (each training uses `threads`, 1)
#
# DVC runs one stage at a time per command, but it releases its repository lock while a
# stage's command runs, so separate `dvc repro --single-item` commands of independent stages
# run side by side; `dvc --wait-for-lock` makes a command wait for the lock instead of
# failing when another one holds it for a moment (to read the pipeline or record a stage in
# dvc.lock). The steps:
#   1. the upstream stages, once (ABLATION_UPSTREAM; default: the main pipeline's `generate`
#      when the default recipe runs);
#   2. every point stage of the recipes (`<recipe>@<point>`), ABLATION_JOBS at a time (xargs);
#   3. each recipe's report (a plain `dvc repro`: it finds every point up to date).
# Each stage is recorded in dvc.lock as it finishes, so an interrupted run resumes where it
# stopped. ABLATION_PIPELINE names another pipeline file of the same layout (the tests use
# one whose stages sleep); GC_ABLATION_DRY_RUN=1 prints the commands instead of running them.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

jobs=${ABLATION_JOBS:-2}
pipeline=${ABLATION_PIPELINE:-ablation/dvc.yaml}
dvc=${DVC:-dvc}
recipes=("$@")
if [ ${#recipes[@]} -eq 0 ]; then
  recipes=(default paper)
fi
# the default recipe's data is the main pipeline's; the paper's (data/paper) is in git
default_upstream=""
if [[ " ${recipes[*]} " == *" default "* ]]; then
  default_upstream=generate
fi
upstream=${ABLATION_UPSTREAM-$default_upstream}

run() {
  if [ "${GC_ABLATION_DRY_RUN:-0}" = 1 ]; then echo "+ $*"; else "$@"; fi
}

pattern=$(IFS='|'; echo "${recipes[*]}")
mapfile -t points < <($dvc stage list --name-only "$pipeline" | grep -E ":($pattern)@")
if [ ${#points[@]} -eq 0 ]; then
  echo "no point stages of ${recipes[*]} in $pipeline" >&2
  exit 2
fi

for stage in $upstream; do
  run $dvc repro "$stage"
done
echo "${#points[@]} points, $jobs at a time: ${points[*]}"
if [ "${GC_ABLATION_DRY_RUN:-0}" = 1 ]; then
  for point in "${points[@]}"; do
    echo "+ $dvc --wait-for-lock repro --single-item $point"
  done
else
  printf '%s\n' "${points[@]}" \
    | xargs -P "$jobs" -I{} $dvc --wait-for-lock repro --single-item {}
fi
for recipe in "${recipes[@]}"; do
  run $dvc repro "$pipeline:report@$recipe"
done
