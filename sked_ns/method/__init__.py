"""What SKED adds to any representation: options, losses, preservation, the edit box, the Eq. 6 sum."""
