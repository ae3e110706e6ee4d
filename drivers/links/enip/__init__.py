"""The EtherNet/IP adapter backend of the link seam (docs/integration.md, "EtherNet/IP")."""
