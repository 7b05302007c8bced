#!/usr/bin/env bash
# Behaviour unchanged across a refactor: the same small estimation runs with two trees' code, compared.
#
#   bash bench/equivalence.sh prep DATA              # files and two tiny checkpoints, made once (this tree's code)
#   bash bench/equivalence.sh run TREE DATA OUT      # the runs with TREE's src/ (a worktree or a git archive)
#   python bench/equivalence.py OUT_A OUT_B          # every CSV of the runs compared (relative 1e-12)
#
# One run per estimation path of the demo and noise pipelines and beyond (n <= 16 each): exp5, exp6, exp8,
# exp10 (shared CNN/U-Net checkpoints), the road-free occupant (rigid + CNN; foreign rigid; persons at 5 %
# noise), sprung, the half car and aggregate=drive. One BLAS thread: byte-identical files need one thread count.
set -u
BIN=$(dirname "$(command -v python3)")
[ -x "$PWD/.venv/bin/python" ] && BIN=$PWD/.venv/bin
export OMP_NUM_THREADS=1
case "${1:-}" in
prep)
  D=$2; mkdir -p "$D"; export PYTHONPATH=$PWD/src
  $BIN/qcm-simulate preset=tiny physics=continuous output=$D/demo.h5 hydra.run.dir=$D/sim >/dev/null
  $BIN/python bench/foreign_sim.py make --out $D/body1.h5 --n 3 --steps 512 --occupant body1 --noise 0.05 --seed 3 >/dev/null
  $BIN/python bench/foreign_sim.py make --out $D/rigid.h5 --n 8 --steps 512 --seed 5 --noise 0.02 >/dev/null
  $BIN/qcm-simulate vehicle=half_car preset=tiny output=$D/hcm.h5 hydra.run.dir=$D/simh >/dev/null
  $BIN/python bench/foreign_sim.py drives --out $D/drives --n 2 --duration 16 --stop-s 4 --change --noise 0.02 --seed 4 >/dev/null
  $BIN/qcm-import input=$D/drives/drives.csv output=$D/drives.h5 recording_column=recording window=400 \
    hydra.run.dir=$D/imp >/dev/null
  $BIN/qcm-train experiment=exp2_physics_continuous data.path=$D/demo.h5 trainer.max_epochs=1 hydra.run.dir=$D/cnn >/dev/null 2>&1
  $BIN/qcm-train experiment=exp9_unet_continuous data.path=$D/demo.h5 trainer.max_epochs=1 hydra.run.dir=$D/unet >/dev/null 2>&1
  ;;
run)
  R=$(cd "$2" && pwd); D=$3; O=$4; mkdir -p "$O"; export PYTHONPATH=$R/src
  CNN=cnn_ckpt=$D/cnn/checkpoints/last.ckpt; UNET=unet_ckpt=$D/unet/checkpoints/last.ckpt
  E() { name=$1; shift; (cd "$R" && $BIN/qcm-estimate "$@" hydra.run.dir=$O/$name progress=false >$O/$name.log 2>&1); echo "$name rc=$?"; }
  E exp5 experiment=exp5_random_init data.path=$D/demo.h5 n_samples=16
  E exp6 experiment=exp6_cnn_init data.path=$D/demo.h5 n_samples=16 $CNN
  E exp10 experiment=exp10_hybrid data.path=$D/demo.h5 n_samples=16 $CNN $UNET n_steps=100
  E exp8 experiment=exp8_occupant_only data.path=$D/demo.h5 n_samples=16 $CNN
  E occ_rigid experiment=occupant_roadfree data.path=$D/demo.h5 n_samples=16 init.cnn=true $CNN "occupant.models=[rigid]" delay=null
  E occ_rigid_foreign experiment=occupant_roadfree data.path=$D/rigid.h5 n_samples=4
  E occ_body1 experiment=occupant_roadfree data.path=$D/body1.h5 n_samples=3
  E sprung experiment=sprung_roadfree data.path=$D/rigid.h5 n_samples=8
  E hcm experiment=hcm_full_observation data.path=$D/hcm.h5 n_samples=8
  E drive experiment=occupant_roadfree data.path=$D/drives.h5 "occupant.models=[rigid]" aggregate=drive restarts.count=0 block_samples=2000
  ;;
*) sed -n 2,11p "$0"; exit 2 ;;
esac
