from omnire_rigid.node import RigidConfig, RigidNode

__all__ = ["RigidConfig", "RigidNode"]
