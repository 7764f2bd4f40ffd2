#!/usr/bin/env bash
# Evaluate square checkpoints on a lent GPU machine's 16 cores (/work/.library/device): eval/eval_sim.py with one
# worker per core, the wrist camera rendered by the GPU through EGL. The machine has torch, numba, scipy, h5py and
# OpenCV but not robosuite, robomimic, MuJoCo, zarr or hydra, and takes at most 64 MiB per call, so prepare here:
#   echo /.whl/ >> .git/info/exclude; echo /.carry/ >> .git/info/exclude
#   pip download (cp312 manylinux wheels; README of the device tool) mujoco==3.9.0 PyOpenGL==3.1.10
#       numcodecs==0.15.2 zarr==2.18.7 hydra-core==1.3.8 omegaconf==2.3.1 Deprecated==1.3.1 termcolor==3.3.0 -d .whl
#   pip wheel --no-deps -w .whl antlr4-python3-runtime==4.9.3 asciitree==0.3.3
#   python -m umi_aug.square.carry_sim pack .carry/sim --wheels .whl/*.whl     # 19.3 MB (no diffusers wheel needed)
#   python -m umi_aug.data.carry pack-file <run>/checkpoints/latest.ckpt .carry/ckpt/<name>.ckpt.s4xz   # 32.4 → 23.2 MB
#   (GL loaders, used only if the machine lacks libEGL: apt-get download libegl1 libglvnd0 libopengl0 libgl1
#    libglx0 libgles2 into .carry/gl)
# then, as the device call's command (carry: .carry):
#   bash eval/lent_gpu_eval.sh <deadline_s> <name> "<eval_sim.py arguments>" [<name> "<arguments>" ...]
# A checkpoint .carry/ckpt/X.s4xz is unpacked to /tmp/ckpt/X (its SHA-256 checked): name it checkpoint=/tmp/ckpt/X.
# The runs go one after another, each with workers=$(nproc) and out_dir=/tmp/evals/<name>; a run still going at
# <deadline_s> after the start is stopped with SIGTERM (eval_sim keeps every finished rollout; rerunning the same
# command here resumes it). The run key (run.json: checkpoint SHA-256, configurations file, horizon, ...) holds no
# path, so a run finished there continues or closes here in the study's own out_dir. Back under $OUT:
# <name>.tar.xz (the out_dir without videos/) and probe.npz (the wrist frames at the first 4 start states, for
#   python -m umi_aug.square.carry_sim probe here.npz --compare <files_at>/probe.npz).
set -uo pipefail
export PYTHONUNBUFFERED=1 MUJOCO_GL=egl
deadline=$1
shift
t0=$(date +%s)
if [ -z "${LENT_SKIP_INSTALL:-}" ]; then  # LENT_SKIP_INSTALL=1: a dry run where the packages are installed
    if ! ldconfig -p | grep -q 'libEGL.so.1' && ls .carry/gl/*.deb > /dev/null 2>&1; then
        for f in .carry/gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
        echo "GL loaders unpacked from .carry/gl"
    fi
    [ -n "$(ls /usr/local/nvidia/share/glvnd/egl_vendor.d/ 2>/dev/null)" ] \
        && export __EGL_VENDOR_LIBRARY_FILENAMES=${__EGL_VENDOR_LIBRARY_FILENAMES:-$(ls /usr/local/nvidia/share/glvnd/egl_vendor.d/*.json | head -n 1)}
    mkdir -p /tmp/site && tar -xJf .carry/sim/site.tar.xz -C /tmp/site || exit 3
    export PYTHONPATH=/tmp/site:$PWD
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null
echo "cores: $(nproc)"
mkdir -p /tmp/ckpt
for f in .carry/ckpt/*.s4xz; do
    [ -e "$f" ] || continue
    name=$(basename "$f" .s4xz)
    [ -e "/tmp/ckpt/$name" ] || python3 -m umi_aug.data.carry unpack-file "$f" "/tmp/ckpt/$name" || exit 4
done
python3 -m umi_aug.square.carry_sim probe "$OUT/probe.npz" || { echo "the square scene does not render here"; exit 5; }
echo "setup: $(( $(date +%s) - t0 )) s"
while [ $# -ge 2 ]; do
    name=$1 args=$2
    shift 2
    left=$(( deadline - ($(date +%s) - t0) ))
    if [ "$left" -lt 30 ]; then echo "$name: not started, $left s left"; continue; fi
    s0=$(date +%s)
    # shellcheck disable=SC2086  # the arguments are words
    timeout -s TERM "$left" python3 eval/eval_sim.py $args workers="$(nproc)" out_dir="/tmp/evals/$name" \
        progress=false > "/tmp/evals_$name.log" 2>&1
    rc=$?
    tail -n 2 "/tmp/evals_$name.log"
    echo "$name: exit $rc after $(( $(date +%s) - s0 )) s; $(wc -l < "/tmp/evals/$name/results.jsonl" 2>/dev/null || echo 0) rollouts"
    cp "/tmp/evals_$name.log" "/tmp/evals/$name/lent_gpu_eval.log" 2>/dev/null
    tar -cJf "$OUT/$name.tar.xz" -C /tmp/evals --exclude=videos "$name"
done
echo "total: $(( $(date +%s) - t0 )) s"
