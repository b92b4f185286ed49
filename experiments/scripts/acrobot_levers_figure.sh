#!/usr/bin/env bash
# The acrobot lines trained on master seeds 1-3 since the learning-rate decay ([73]-[117]): each run's last training
# evaluation (~200K), grouped by line, against issue #5's 700 and TD-MPC2's measured 278.1 ([21]).
#   bash experiments/scripts/acrobot_levers_figure.sh [PREFIX]
# (default PREFIX experiments/results/figures/acrobot-levers-master-seeds123-200k; run from the project root with the
# package importable, e.g. PYTHONPATH=src or the venv; $PYTHON picks the interpreter, default python3)
set -eu
out=${1:-experiments/results/figures/acrobot-levers-master-seeds123-200k}
R=experiments/results/cfc-acrobot-recipe
runs() {  # FOLDER NAME: FOLDER/NAME1,FOLDER/NAME2,FOLDER/NAME3 (NAME ends in "seed")
    echo "$R-$1/$2"1,"$R-$1/$2"2,"$R-$1/$2"3
}
"${PYTHON:-python3}" experiments/scripts/final_returns_figure.py \
    --line "lr decay, every 2 [73]=$(runs lrdecay-h200-200k acrobot-recipe-lrdecay-seed)" \
    --line "pink seed phase [76]=$(runs pinkseed-h200-200k acrobot-recipe-pinkseed-seed)" \
    --line "2 updates/step [77]=$(runs utd2-h200-200k acrobot-recipe-utd2-seed)" \
    --line "every 4 [84]=$(runs ar4-ar8-h100-200k acrobot-recipe-ar4-seed)" \
    --line "every 8 [84]=$(runs ar4-ar8-h100-200k acrobot-recipe-ar8-seed)" \
    --line "every 4, 3 updates [85]=$(runs utd3-h200-200k acrobot-recipe-utd3-seed)" \
    --line "every 4, 5 Q heads [88] [92]=$R-gamma995-numq5-h100-200k/acrobot-recipe-numq5-seed1,$R-numq5-seeds23-h100-200k/acrobot-recipe-numq5-seed2,$R-numq5-seeds23-h100-200k/acrobot-recipe-numq5-seed3" \
    --line "every 6, gamma 0.99 [93]=$(runs ar6-h100-200k acrobot-recipe-ar6-seed)" \
    --line "every 6, gamma 0.99 again [103]=$(runs gamma99-relaunch-h100-200k acrobot-recipe-gamma99-relaunch-seed)" \
    --line "every 6, 3 updates [94]=$(runs ar6-utd3-h100-200k acrobot-recipe-ar6-utd3-seed)" \
    --line "every 6, gamma 0.97 [97]=$(runs gamma-h100-200k acrobot-recipe-gamma97-seed)" \
    --line "every 6, gamma 0.985 (recipe) [97]=$(runs gamma-h100-200k acrobot-recipe-gamma985-seed)" \
    --line "every 6, gamma 0.985 again (recipe) [102]=$(runs gamma985-relaunch-h100-200k acrobot-recipe-gamma985-relaunch-seed)" \
    --line "every 6, window 32 [101]=$(runs h32-h100-200k acrobot-recipe-h32-seed)" \
    --line "every 6, gamma 0.985, observation skip [104]=$(runs obsskip-h200-200k acrobot-recipe-obsskip-seed)" \
    --line "every 6, gamma 0.985, tau 0.02 [105]=$(runs tau02-h100-200k acrobot-recipe-tau02-seed)" \
    --line "every 6, gamma 0.985, CfC backbone 256 [106]=$(runs backbone256-h100-200k acrobot-recipe-bb256-seed)" \
    --line "every 6, gamma 0.985, CfC backbone 256 again [107]=$(runs backbone256-relaunch-h100-200k acrobot-recipe-bb256-relaunch-seed)" \
    --line "every 6, gamma 0.985, CfC backbone 512 [108]=$(runs backbone512-h100-200k acrobot-recipe-bb512-seed)" \
    --line "every 6, gamma 0.985, 512 windows/update [109]=$(runs batch512-h100-200k acrobot-recipe-batch512-seed)" \
    --line "every 6, gamma 0.985, MPPI 12 iterations [110]=$(runs iter12-h100-200k acrobot-recipe-iter12-seed)" \
    --line "every 6, gamma 0.985, exploration floor 0.2 [112]=$(runs explorefloor02-h100-200k acrobot-recipe-explorefloor02-seed)" \
    --line "every 6, gamma 0.985, exploration floor 0.5 [112]=$(runs explorefloor05-h100-200k acrobot-recipe-explorefloor05-seed)" \
    --line "every 6, gamma 0.985, 401 two-hot bins [117]=$(runs bins401-h100-200k acrobot-recipe-bins401-seed)" \
    --bar 700 --reference "TD-MPC2 [21]=278.1" --run-names "master seed 1,master seed 2,master seed 3" \
    --title "acrobot-swingup, cfc-zp-det, master seeds 1-3 at ~200K: the lines since the learning-rate decay" \
    --out "$out"
