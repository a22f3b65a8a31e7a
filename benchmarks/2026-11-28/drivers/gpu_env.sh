# Sourced by the GPU session scripts (gpu_session.sh, gpu_pack.sh) on a machine with PyTorch 2.11
# (CUDA 13) in $PY: puts that PyTorch's libtorch (its CUDA part included), its CUDA runtime and
# CUPTI, and MuJoCo on the library path, so that a CPU-only-linked promptdt runs on the GPU.
TL=$("$PY" -c 'import os, torch; print(os.path.join(os.path.dirname(torch.__file__), "lib"))')
SP=$(dirname "$(dirname "$TL")")
CUDART=$(dirname "$(find "$SP/nvidia" -name 'libcudart.so.13*' | head -1)")
CUPTI=$(dirname "$(find "$SP/nvidia" -name 'libcupti.so.13*' | head -1)")
export LD_LIBRARY_PATH=$PWD/third_party/mujoco/lib:$TL:$CUDART:$CUPTI
export OMP_WAIT_POLICY=PASSIVE
