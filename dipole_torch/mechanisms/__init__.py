"""The mechanisms DIPOLE plugs into Algorithm 2, one module each; each choice of an option is
an object, "off" included (see ``dipole_torch.Dipole``)."""
