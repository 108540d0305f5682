"""The training step's engine: what one step of nerfstudio's loop runs through besides the render itself.

* `training_data`: the training views a step draws, on the device;
* `initialisation`: the Gaussians a run starts from;
* `losses`, `ssim`, `fused_ssim`: the photometric loss (L1 and D-SSIM, its fused CUDA kernels);
* `metrics`: PSNR, SSIM and LPIPS for evaluation;
* `adam`: the fused optimizer step;
* `train_graphs`: the deformation field's and the optimizers' CUDA graphs;
* `recipe`: the training recipe's settings (precision, fused layers, composition).

May import: `render`, `compaction`, `redundancy`, `ops`, and the root's `deformation` and `errors`. Never the
plugin's face (`garo_model`, `garo_strategy`, `config`), `state`, `tools` or `bench`.
"""
