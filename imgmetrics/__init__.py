"""imgmetrics: image-quality metrics shared by training and evaluation.

* :mod:`imgmetrics.psnr_ssim`: PSNR and SSIM of an image pair, the 3DGS definitions, with the
  PSNR cap of the evaluation's means;
* :mod:`imgmetrics.ssim`: the SSIM's building blocks (its Gaussian window and per-pixel map, which
  the training loss and its C++ kernel share) and the layout conversion the metrics use
  (:func:`imgmetrics.ssim.to_bchw`);
* :mod:`imgmetrics.lpips`: LPIPS (AlexNet / VGG16 with the official linear heads), its weights
  read from safetensors;
* :mod:`imgmetrics.floor`: the floor's flat image (the training views' mean colour), the one
  definition of its colour.

Ground floor (tests/test_import_layers.py): it imports no stage, so the training loss and the
evaluation metrics compute the same numbers without importing each other.
"""
