#!/usr/bin/env bash
# Generate a umesh dataset on a Slurm cluster: one array task per shard group, then merge.
#
#   sbatch --array=0-19 scripts/slurm_dataset.sh SEG.nii.gz 5 /shared/datasets/patient42
#   # when all tasks are done (or with --dependency=afterok:<jobid>):
#   umesh dataset merge /shared/datasets/patient42/part_* --out /shared/datasets/patient42/all
#
# Every task runs the same configuration with --shard k/N (N = the array size), writing its
# shard files into its own folder; sample i depends only on (seed, i), so the merged dataset is
# byte for byte the one a single machine would write. A task that is killed and resubmitted
# resumes where it stopped. Arguments: segmentation, organ label, output root; extra
# arguments are passed to `umesh dataset generate` (e.g. --samples 1000 --seed 7).
#SBATCH --job-name=umesh-dataset
#SBATCH --cpus-per-task=2
#SBATCH --mem=4G
#SBATCH --time=02:00:00
set -euo pipefail
seg=$1; label=$2; root=$3; shift 3
k=${SLURM_ARRAY_TASK_ID:?run with sbatch --array}
n=${SLURM_ARRAY_TASK_COUNT:?run with sbatch --array}
umesh=${UMESH:-umesh}
export RAYON_NUM_THREADS=${SLURM_CPUS_PER_TASK:-2}
"$umesh" dataset generate "$seg" --organ-label "$label" --shard "$k/$n" --out "$root/part_$k" "$@"
