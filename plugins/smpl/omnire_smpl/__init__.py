from omnire_smpl.node import SMPLConfig, SMPLNode

__all__ = ["SMPLConfig", "SMPLNode"]
