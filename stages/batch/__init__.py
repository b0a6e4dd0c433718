"""batch: many scenes and prompts as one Snakemake workflow (`goi batch CONFIG`).

Owns: the batch configuration (`config`, schema goi.batch), the workflow shipped as package
data (`workflow/Snakefile`: one rule per goi stage, orchestration only) and its run and
summary (`run`). It runs goi's commands as jobs and imports the layers below only to check
the configuration (scenes, prompt names). Needs the optional extra `goi[batch]` (Snakemake).
"""
