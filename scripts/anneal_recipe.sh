# The annealing recipe of docs/RESULTS.md ("Annealed at equal budget, three seeds: the shipped pairs"): a trained
# run continued from its weights (--init-from: a run folder, whose best checkpoint is read, or a weights file) with
# whole-image rays, a half-cosine learning rate LR -> LR_FINAL (default 3e-4 -> 3e-6), no validation, and its own
# seed, ANNEAL_SEED. Sourced by scripts/run_study.sh ('-an' runs), anneal_pair_study.sh and anneal_study.sh:
#   source scripts/anneal_recipe.sh; anneal_flags FROM [LR [LR_FINAL]]   # sets the array ANNEAL_FLAGS
#   depthnerf train ... --seed "$ANNEAL_SEED" "${ANNEAL_FLAGS[@]}" --max-steps N
export ANNEAL_SEED=1
anneal_flags() {
  ANNEAL_FLAGS=(--init-from "$1" --schedule.bbox_steps 0 --schedule.lr_schedule cosine --schedule.lr "${2:-3e-4}"
                --schedule.lr_final "${3:-3e-6}" --log.val_every 0)
}
export -f anneal_flags
