#!/usr/bin/env bash
# The GPU check of docs/benchmarks.md ("On a GPU (H200)"), in one run: the CUDA tests (kernels and a whole window
# fit against the CPU), the encoding bench on the GPU, the default row's nerf_fit (cpu preset), and the L preset on
# a 1280x720 window for L_STEPS steps (time-stamped progress: seconds per 100 steps and per rendered image).
#
# The rows are made on a machine with Open3D (synth needs it; nerf_fit does not), then copied to the GPU machine:
#   pag all --seq synth_row --to windows --data-root D
#   pag all --seq synth_l16 --to windows --data-root D --set synth.preset=bup20 --set synth.n_frames=16 \
#       --set synth.n_labelled=1 --set synth.write_bag=false
# and on the GPU machine (its python3 holds a CUDA build of torch; dask and pycocotools installed or on PYTHONPATH):
#   DATA_ROOT=D OUT=results scripts/gpu_check.sh
# Then `pag all --seq synth_row --data-root D --from panoptic_fusion` anywhere with Open3D scores the GPU's fits.
set -u
cd "$(dirname "$0")/.."
: "${DATA_ROOT:?set DATA_ROOT to the data folder holding synth_row and synth_l16}" "${OUT:?set OUT to a folder}"
PY=${PY:-python3}
export PYTHONUNBUFFERED=1 PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
mkdir -p "$OUT"
T0=$(date +%s); LOG=$OUT/log.txt
mark() { echo "== $1 at $(( $(date +%s) - T0 )) s" >> "$LOG"; }
stamp() { while IFS= read -r l; do printf '%s %s\n' "$(( $(date +%s) - T0 ))" "$l"; done; }
mark build
$PY -c "from nerf._ext import load_permuto_ext as load; print('cuda kernels', load('cuda') is not None)" >> "$LOG" 2>&1
mark tests-and-encoding   # the tests' CPU fits run beside the GPU bench
timeout "${TEST_S:-150}" $PY -m pytest -q -m cuda -p no:cacheprovider --durations=4 tests/nerf/test_encoding.py \
  tests/stress/test_numerical_stress.py tests/nerf/test_cuda.py > "$OUT/tests.txt" 2>&1 &
TESTS=$!
timeout "${ENC_S:-80}" $PY -m pipeline.cli bench encoding --device cuda --points 1048576 --repeats 5 --out "$OUT" \
  >> "$LOG" 2>&1
wait $TESTS; echo "tests rc $?" >> "$LOG"; tail -12 "$OUT/tests.txt" >> "$LOG"
mark default-row
timeout "${ROW_S:-170}" $PY -m pipeline.cli nerf_fit --seq synth_row --data-root "$DATA_ROOT" \
  --set run.progress_interval_s=20 2>&1 | stamp >> "$LOG"
mark L-window
timeout "${L_S:-110}" $PY -m pipeline.cli nerf_fit --seq synth_l16 --data-root "$DATA_ROOT" --set nerf_fit.preset=L \
  --set nerf_fit.model.steps="${L_STEPS:-600}" --set nerf_fit.panoptic.steps=200 --set nerf_fit.render_scale=1 \
  --set run.progress_interval_s=5 2>&1 | stamp >> "$LOG"
cp "$DATA_ROOT/processed/synth_l16/window_metrics.parquet" "$OUT/l_window_metrics.parquet" 2>> "$LOG"
cp "$DATA_ROOT/processed/synth_row/window_metrics.parquet" "$OUT/row_window_metrics.parquet" 2>> "$LOG"
mark done
