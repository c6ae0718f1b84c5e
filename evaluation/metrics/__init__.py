"""What a run is measured by: pose accuracy and the success criteria (:mod:`.pose`), Sim(3)
alignment (:mod:`.align`, :mod:`.align_run`), image metrics (:mod:`.images_cli`, over
:mod:`imgmetrics`; LPIPS weights :mod:`.lpips_convert`) and floaters (:mod:`.floaters`)."""
