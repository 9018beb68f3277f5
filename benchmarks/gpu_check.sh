#!/usr/bin/env bash
# The GPU check of a lent CUDA machine, as one short script: the tests that take the
# `device` fixture, on CUDA, then bench_batched.py at B = 1, 8 and 32 on CUDA, then the same at B = 8 on
# the CPU for the ratio. The machine's own python3 (3.12) and torch are used; kornia and PyMaxflow, which
# it lacks, come as wheels in .whl/ (git-ignored through .git/info/exclude), fetched beforehand with
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_17_x86_64 -d .whl kornia kornia_rs PyMaxflow
# tests/io, which needs the io extra and has no CUDA test, is left out. Output goes to $OUT/gpu_check.log
# when OUT is set, else to stdout.
set -uo pipefail
cd "$(dirname "$0")/.."
log=${OUT:-/tmp}/gpu_check.log
{
    if compgen -G ".whl/*.whl" >/dev/null; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
        export PYTHONPATH=/tmp/site:$PWD
    fi
    export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
    python3 -c "import torch, kornia, maxflow; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'kornia', kornia.__version__)"
    echo "== CUDA tests"
    timeout 240 python3 -m pytest -p no:cacheprovider -q --device cuda -k cuda tests --ignore=tests/io -W ignore::UserWarning
    echo "== bench_batched.py, CUDA"
    timeout 240 python3 benchmarks/bench_batched.py --device cuda --windows 32 --batch-sizes 1 8 32 --threads 0
    echo "== bench_batched.py, CPU (16 cores, same machine)"
    timeout 120 python3 benchmarks/bench_batched.py --device cpu --windows 8 --batch-sizes 8 --threads 0
} 2>&1 | tee "$log"
