#!/bin/bash
# Carry .gpu_site (hydra, omegaconf, antlr4 copied from the venv) and .gpu_yaml (PyYAML) where the GPU machine lacks them;
# OUT: a folder for tests.txt and bench_gpu.txt. Results: docs/measurements/scaling.md, "Gauss-Newton on the GPU".
# issue 33 item 3 on the lent GPU: environment, GN-on-GPU tests, then the bench (each step bounded)
cd "$(dirname "$0")/.."
export PYTHONPATH=$PWD/.gpu_site
python3 -c "import yaml" 2>/dev/null || export PYTHONPATH=$PYTHONPATH:$PWD/.gpu_yaml
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import sys,torch,lightning,h5py,scipy,hydra,omegaconf; print(sys.version.split()[0], torch.__version__, torch.cuda.is_available(), lightning.__version__, hydra.__version__)" 2>&1 | tail -2
export PYTHONPATH=$PWD/src:$PYTHONPATH
timeout ${TEST_S:-150} python3 -m pytest -q -p no:cacheprovider tests/test_front_gpu.py -k "gauss_newton or equation_error" 2>&1 | tail -25 | tee $OUT/tests.txt
timeout ${BENCH_S:-400} python3 bench/bench_gpu.py --cpu-single 256 --gpu-sizes 256 4096 17000 170000 --budget-s $(( ${BENCH_S:-400} - 20 )) "$@" 2>&1 | tee $OUT/bench_gpu.txt
