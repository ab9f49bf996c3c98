#!/bin/bash
# Run a parjam campaign as resumable stages; called by slurm.sbatch and pbs.pbs (also usable
# by hand: LAUNCH="mpirun -n 4" scripts/hpc/run_stages.sh stages.txt).
#
#   run_stages.sh STAGES_FILE
#
# STAGES_FILE has one stage per line, "NAME: parjam arguments", e.g.
#   pack: pack --dim 3 --n 100000 --members 4 --dphi 1e-3 --out $OUT/packings
#   dos:  dos --method kpm $OUT/packings/member*_dphi1.0e-03.h5 --out $OUT/dos.h5
# ($OUT expands to the scratch run directory; blank lines and # comments are skipped).
#
# Resume on requeue: a stage that finished leaves $OUT/.done/NAME and is skipped when the job
# runs again; an unfinished stage is rerun with the *same command*, so commands that skip their
# finished work (parjam pack skips members whose files exist, and resumes the member in progress
# from its checkpoint, --checkpoint-every, default 300 s) lose at most that interval.
# Output (HDF5 files, -log_view per stage, stdout/stderr per stage) goes to $OUT on scratch;
# copy results home with PARJAM_COPY_BACK=DIR.
#
# Environment: LAUNCH (MPI launcher with rank count, required), OUT (run directory, required),
# PARJAM (the parjam command, default: python -m parjam of the checkout's .venv),
# PARJAM_PETSC_OPTS (extra PETSc options for every stage, e.g. "-modes_st_mat_mumps_icntl_7 5").
set -uo pipefail

stages_file=${1:?usage: run_stages.sh STAGES_FILE}
: "${LAUNCH?set LAUNCH, e.g. 'srun' or 'mpirun -n 64' (empty: serial)}"
: "${OUT:?set OUT to a scratch directory}"
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
root=$(cd "$here/../.." && pwd)
PARJAM=${PARJAM:-"$root/.venv/bin/python -m parjam"}
export OUT OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} OPENBLAS_NUM_THREADS=1

mkdir -p "$OUT/.done" "$OUT/logs"
log() { echo "[$(date -u +%FT%TZ)] $*" | tee -a "$OUT/logs/campaign.log"; }

status=0
while IFS= read -r line || [ -n "$line" ]; do
    line=${line%%#*}
    [[ "$line" =~ ^[[:space:]]*$ ]] && continue
    name=$(echo "${line%%:*}" | tr -d '[:space:]')
    args=$(eval echo "${line#*:}")  # expands $OUT and globs at run time (after earlier stages)
    if [ -e "$OUT/.done/$name" ]; then
        log "stage $name: done before, skipped"
        continue
    fi
    log "stage $name: $LAUNCH $PARJAM $args"
    # shellcheck disable=SC2086  # word splitting of the launcher and arguments is intended
    # </dev/null: mpirun/srun would otherwise read the rest of the stages file from stdin
    $LAUNCH $PARJAM $args ${PARJAM_PETSC_OPTS:-} -log_view ":$OUT/logs/$name.log_view.txt" \
        </dev/null >>"$OUT/logs/$name.out" 2>>"$OUT/logs/$name.err"
    rc=$?
    if [ $rc -ne 0 ]; then
        log "stage $name: failed with exit status $rc (see $OUT/logs/$name.err)"
        status=$rc
        break
    fi
    date -u +%FT%TZ >"$OUT/.done/$name"
    log "stage $name: finished"
done <"$stages_file"

if [ $status -eq 0 ] && [ -n "${PARJAM_COPY_BACK:-}" ]; then
    mkdir -p "$PARJAM_COPY_BACK" && cp -r "$OUT"/. "$PARJAM_COPY_BACK"/ && log "copied to $PARJAM_COPY_BACK"
fi
exit $status
