"""Paper 000's improved Richardson-Lucy: the iteration count predicted from the blur kernel by a small ensemble of
back-propagation networks (numpy), trained on simulated frames.

* :mod:`.features`: the kernel's SUMFC feature and the "optimal iteration" a training sample is labelled with;
* :mod:`.ebpnn`: the 1-10-1 networks, improved bagging and just-in-time refinement (the EBPNN);
* :mod:`.deblurrer`: :class:`.deblurrer.IterationNetDeblurrer`, the deblurrer using the shipped weights;
* :mod:`.train`: regenerates ``iteration_net.npz`` (``python -m starenv.agents.restore.iteration.train --out PATH``).
"""
