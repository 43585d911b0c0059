"""Learned baselines of the paper (Sec. IV-B), adapted to onboard signals and the PRML2 ONNX contract.

Every baseline maps a raw window ``onboard`` (B, L, 9) [SI] to ``(mean, var)`` (B, L - H, 5) like
:class:`prml2_edge.training.model.Prml2Model`, so it exports with the same graph contract and runs
through the same streaming localiser and NumPy EKF in ``prml2 evaluate``:

* ``nn-vdm``: GRU vehicle-dynamics model (NN-VDM);
* ``dl-avl``: LSTM (DL-AVL);
* ``rnn-ekf``: GRU with attention and a learned adaptive-noise head (RNN-EKF);
* ``backprop-kf``: a per-step feed-forward observation model trained end to end through the
  differentiable EKF (Backprop-KF, adapted to onboard signals as the paper did).
"""

from prml2_edge.training.baselines.models import BASELINES, BaselineConfig, build_baseline

__all__ = ["BASELINES", "BaselineConfig", "build_baseline"]
