"""Evaluation: held-out metrics on the light stage (evaluate, with its metrics and predictors), the
paper's ablation table and temporal-stability protocol, real faces (CroppedYale), real footage, the
README's before/after picture, and the reports every measurement writes to bench/results/."""
