#!/usr/bin/env bash
# Train square policies side by side on a lent GPU machine (/work/.library/device; docs/gpu_training_check.md),
# and send back what eval_sim needs. The machine has torch but not zarr/numcodecs/hydra/omegaconf/diffusers and
# takes at most 64 MiB per call, so prepare here, once:
#   echo /.whl/ >> .git/info/exclude; echo /.carry/ >> .git/info/exclude
#   pip download (cp312 manylinux wheels; README of the device tool) zarr==2.18.7 numcodecs==0.15.2 hydra-core==1.3.8
#       omegaconf==2.3.1 diffusers==0.42.1 -d .whl; pip wheel --no-deps -w .whl antlr4-python3-runtime==4.9.3
#       asciitree==0.3.3 Deprecated==1.3.1
#   python -m umi_aug.data.carry pack square_demos/square_expert_fisheye84.zarr.zip .carry/square50   # 36 MB
# then, as the device call's command (carry: .whl, .carry):
#   bash train/lent_gpu.sh <deadline_s> <bundle> <name> "<train.py overrides>" [<name> "<overrides>" ...]
# Each run trains in the background with its overrides (task=square on the unpacked bundle, device=cuda); at
# <deadline_s> after the start every run still going is stopped (its last checkpoint_every_steps checkpoint is
# kept, and the log says at which step). Back under $OUT/<name>/: logs.jsonl, train.log's tail, and the slim
# float16 checkpoint (umi_aug.policy.checkpoint.slim_checkpoint) in parts of 15 MiB:
#   cat <files_at>/<name>/slim.ckpt.part* > <name>.ckpt     # here; then eval/eval_sim.py checkpoint=<name>.ckpt
set -uo pipefail
export PYTHONUNBUFFERED=1
deadline=$1 bundle=$2
shift 2
t0=$(date +%s)
# LENT_SKIP_INSTALL=1 LENT_DEVICE=cpu: a dry run on a machine that has the packages (the script's test)
[ -n "${LENT_SKIP_INSTALL:-}" ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null
nproc
python3 -m umi_aug.data.carry unpack "$bundle" /tmp/data.zarr > /dev/null 2> /tmp/unpack.err || { cat /tmp/unpack.err; exit 4; }
echo "setup: $(( $(date +%s) - t0 )) s"
names=()
while [ $# -ge 2 ]; do
    name=$1 over=$2
    shift 2
    names+=("$name")
    mkdir -p "$OUT/$name"
    # shellcheck disable=SC2086  # the overrides are words
    python3 train/train.py task=square task.dataset_path=/tmp/data.zarr device=${LENT_DEVICE:-cuda} hydra.run.dir="/tmp/runs/$name" \
        training.progress_bar=false $over > "/tmp/$name.log" 2>&1 &
    echo "$name: pid $! overrides: $over"
done
while [ -n "$(jobs -r)" ] && [ $(( $(date +%s) - t0 )) -lt "$deadline" ]; do sleep 5; done
for j in $(jobs -rp); do kill "$j"; echo "stopped pid $j at the deadline"; done
wait
for name in "${names[@]}"; do
    run=/tmp/runs/$name
    tail -n 20 "/tmp/$name.log" > "$OUT/$name/train_tail.log"
    cp "$run/logs.jsonl" "$OUT/$name/" 2>/dev/null
    last=$(tail -n 1 "$run/logs.jsonl" 2>/dev/null)
    echo "$name: last log row $last"
    if [ -f "$run/checkpoints/latest.ckpt" ]; then
        python3 -c "import sys; from umi_aug.policy.checkpoint import slim_checkpoint as s; s(*sys.argv[1:], half=True)" \
            "$run/checkpoints/latest.ckpt" "/tmp/$name.slim.ckpt" \
            && split -b 15M -d "/tmp/$name.slim.ckpt" "$OUT/$name/slim.ckpt.part" \
            && python3 -c "import sys,torch; p=torch.load(sys.argv[1], weights_only=True); print(sys.argv[2], 'step', \
p['pickles']['global_step'])" "/tmp/$name.slim.ckpt" "$name"
    else
        echo "$name: no checkpoint"; tail -n 5 "/tmp/$name.log"
    fi
done
echo "total: $(( $(date +%s) - t0 )) s"
