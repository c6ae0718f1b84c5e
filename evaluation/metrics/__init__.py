"""What a run is measured by: pose accuracy and the success criteria (:mod:`.pose`), Sim(3)
alignment (:mod:`.align`, :mod:`.align_run`), image metrics (:mod:`.image`, :mod:`.images_cli`,
LPIPS weights :mod:`.lpips_convert`) and floaters (:mod:`.floaters`)."""
