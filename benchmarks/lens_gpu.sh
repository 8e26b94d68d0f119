#!/usr/bin/env bash
# Lens correction speed with the torch backend on a CUDA GPU (issue 19: <= 1.25x the
# decode+encode floor, geometry unchanged), for a one-shot device machine: nothing is
# installed, nothing is downloaded; missing modules are named and the script stops.
#
# Run from the repository root, with the Seneca photos carried into the working tree:
#   benchmarks/lens_gpu.sh [PHOTOS_DIR]
# PHOTOS_DIR defaults to the first folder of JPEGs among benchmarks/out/seneca-subset,
# shared/data/seneca-subset, ../shared/data/seneca-subset, /work/shared/data/seneca-subset;
# else tests/mapping/data (2 photos, repeated: still a valid same-run ratio, say so).
# The torch test of tests/mapping (when pytest is there), then two runs of
# benchmarks/lens.py, each under `timeout`: 2 threads (the threads of the 2-core figures)
# and 8 threads; ImageMagick and calibration sections skipped (CPU-only goals measured
# elsewhere); at most 45 + 2 x 110 s. Each run prints its headline ('lens: ...') on its last line.
set -u
REPO=$(cd "$(dirname "$0")/.." && pwd) || exit 2
cd "$REPO" || exit 2
PY=${PYTHON:-python3}
command -v "$PY" >/dev/null || PY=python
echo "== $(date -u +%FT%TZ) $(git rev-parse --short HEAD 2>/dev/null || echo 'no git') $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg)"
nvidia-smi -L 2>/dev/null || echo "nvidia-smi: not available"
"$PY" -c "import torch; print('torch', torch.__version__, 'cuda available:', torch.cuda.is_available())" \
    || { echo "lens_gpu: torch does not import; nothing measured"; exit 3; }
missing=$("$PY" - <<'EOF'
import importlib.util
names = ["numpy", "cv2", "simplejpeg", "piexif", "pyproj", "tqdm", "torch", "kornia"]
print(" ".join(n for n in names if importlib.util.find_spec(n) is None))
EOF
)
if [ -n "$missing" ]; then echo "lens_gpu: missing Python modules: $missing (nothing installed); nothing measured"; exit 3; fi
cuda=$("$PY" -c "import torch; print(int(torch.cuda.is_available()))")
[ "$cuda" = 1 ] || echo "lens_gpu: WARNING no CUDA device: the torch backend runs on the CPU"

# skyfix from this tree without installing it: the package-dir layout of pyproject.toml
# (skyfix.mapping = mapping/, ...) rebuilt as symlinks in a temporary folder.
# Everything Python runs from / : with -c, -m or a child process the current folder comes
# first on sys.path, and the tree's own skyfix/ is only the core.
if ! (cd / && "$PY" -c "import skyfix.mapping.batch_torch" 2>/dev/null); then
    shim=$(mktemp -d)/site
    mkdir -p "$shim/skyfix"
    for f in skyfix/*; do ln -s "$PWD/$f" "$shim/skyfix/$(basename "$f")"; done
    for pkg in thermal crps tags mapping fusion drivers datasets; do ln -s "$PWD/$pkg" "$shim/skyfix/$pkg"; done
    export PYTHONPATH="$shim${PYTHONPATH:+:$PYTHONPATH}"
    (cd / && "$PY" -c "import skyfix.mapping.batch_torch") || { echo "lens_gpu: skyfix does not import from this tree"; exit 3; }
    echo "skyfix imported from this tree through $shim"
fi

photos=${1:-}
[ -z "$photos" ] || photos=$(cd "$photos" && pwd)
if [ -z "$photos" ]; then
    for d in benchmarks/out/seneca-subset shared/data/seneca-subset ../shared/data/seneca-subset \
             /work/shared/data/seneca-subset tests/mapping/data; do
        if ls "$d"/*.jpg >/dev/null 2>&1; then photos=$(cd "$d" && pwd); break; fi
    done
fi
echo "photos: $photos ($(ls "$photos"/*.jpg | wc -l) JPEGs)"
dev=cuda; [ "$cuda" = 1 ] || dev=cpu
rc=0
# The torch-vs-OpenCV test on the device too (its CUDA cases skip on machines without one).
if (cd / && "$PY" -c "import pytest") 2>/dev/null; then
    echo "== pytest tests/mapping/test_mapping_batch.py -k torch_backend"
    (cd / && timeout 45 "$PY" -m pytest -q -p no:cacheprovider --rootdir "$REPO" \
        "$REPO/tests/mapping/test_mapping_batch.py" -k torch_backend -rs 2>&1 | tail -4)
fi
for threads in 2 8; do
    echo "== lens.py --backend torch --device $dev --threads $threads ($(date -u +%T) UTC)"
    (cd / && timeout 110 "$PY" "$REPO/benchmarks/lens.py" --photos "$photos" --backend torch --device "$dev" \
        --threads "$threads" --no-imagemagick --no-calibration --rounds 3 2>&1 | tr '\r' '\n' \
        | grep -v '^lens correct'; exit "${PIPESTATUS[0]}")
    r=$?
    echo "== exit status $r (threads $threads)"
    [ "$r" = 0 ] || rc=1
done
exit $rc
